"""The keyframe gate (``stack.keyframes``): which images the detector runs on, from the wheel odometry
seen before each image; the pipeline and the live run's detector thread pass the same images."""
import numpy as np
import pytest

from stack.keyframes import KeyframeGate, KeyframeSettings
from stack.messages import CameraFrame, CameraInfo, LidarScan, WheelOdometry

INFO = CameraInfo(width=4, height=3, K=np.eye(3))


def _frame(t):
    return CameraFrame(stamp=t, info=INFO, rgb=np.zeros((3, 4, 3), np.uint8))


def _odom(t, x=0.0, yaw_deg=0.0):
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = x
    return WheelOdometry(stamp=t, T_odom_base=T, v=0.0, w=0.0)


def _drive(gate, poses):
    """Feed (t, x, yaw) wheel poses, one image after each; the stamps of the images that pass."""
    passed = []
    for t, x, yaw in poses:
        gate.on_wheel_odometry(_odom(t, x, yaw))
        if gate.passes(_frame(t)):
            passed.append(round(t, 3))
    return passed


def test_off_passes_every_image():
    gate = KeyframeGate(KeyframeSettings())
    assert not gate.settings.enabled
    assert _drive(gate, [(0.1 * i, 0.0, 0.0) for i in range(20)]) == [round(0.1 * i, 3) for i in range(20)]
    assert gate.held == 0


def test_a_still_robot_looks_once_per_interval():
    gate = KeyframeGate(KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0, max_interval_s=1.0))
    passed = _drive(gate, [(0.1 * i, 0.0, 0.0) for i in range(31)])  # 3 s standing
    assert passed == [0.0, 1.0, 2.0, 3.0]
    assert gate.passed == 4 and gate.held == 27
    never = KeyframeGate(KeyframeSettings(min_motion_m=0.1, max_interval_s=0.0))
    assert _drive(never, [(0.1 * i, 0.0, 0.0) for i in range(31)]) == [0.0]  # 0: no looking by time


def test_travel_and_turn_pass_images():
    s = KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0, max_interval_s=0.0)
    # 2.5 cm per image: every fourth image has travelled 10 cm since the last passed one
    assert _drive(KeyframeGate(s), [(0.1 * i, 0.025 * i, 0.0) for i in range(13)]) == [0.0, 0.4, 0.8, 1.2]
    # turning on the spot, 2 degrees per image: every third image has turned 6 >= 5 degrees
    assert _drive(KeyframeGate(s), [(0.1 * i, 0.0, 2.0 * i) for i in range(10)]) == [0.0, 0.3, 0.6, 0.9]
    only_turns = KeyframeSettings(min_turn_deg=5.0, max_interval_s=0.0)
    assert _drive(KeyframeGate(only_turns), [(0.1 * i, 0.025 * i, 0.0) for i in range(13)]) == [0.0]


def test_without_wheel_odometry_every_image_passes():
    gate = KeyframeGate(KeyframeSettings(min_motion_m=0.1, max_interval_s=5.0))
    assert all(gate.passes(_frame(0.1 * i)) for i in range(10))


def test_an_image_detected_elsewhere_is_the_new_reference():
    gate = KeyframeGate(KeyframeSettings(min_motion_m=0.1, max_interval_s=0.0))
    gate.on_wheel_odometry(_odom(0.0, 0.0))
    assert gate.passes(_frame(0.0))
    gate.on_wheel_odometry(_odom(0.5, 0.08))
    gate.mark(_frame(0.5))  # e.g. detections from a cache
    gate.on_wheel_odometry(_odom(0.6, 0.12))
    assert not gate.passes(_frame(0.6))  # 4 cm from the marked image, 12 from the first
    gate.on_wheel_odometry(_odom(0.7, 0.19))
    assert gate.passes(_frame(0.7))


def _stream(n=40):
    """Scans, wheel odometry and images as the simulator gives them: standing 1 s, then 0.25 m/s."""
    for i in range(n):
        t = 0.1 * i
        yield _odom(t, 0.0 if t < 1.0 else 0.25 * (t - 1.0))
        yield LidarScan(stamp=t, points=np.zeros((1, 3)), times_s=np.zeros(1))
        yield _frame(t)


class _Counting:
    def __init__(self):
        self.stamps = []

    def detect(self, frame):
        self.stamps.append(round(frame.stamp, 3))
        return []


class _StillOdometry:
    def process(self, scan):
        return np.eye(4)

    def pose_at(self, t):
        return np.eye(4)

    def trajectory(self):
        return np.zeros(0), np.zeros((0, 4, 4))


@pytest.mark.parametrize("every", [1, 2])
def test_pipeline_and_detector_thread_pass_the_same_images(every):
    from stack.pipeline import DopeSlam
    from testbed.run import _Ahead

    s = KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0, max_interval_s=0.5)
    in_loop = _Counting()
    pipe = DopeSlam(_StillOdometry(), in_loop, np.eye(4), {}, detect_every=every, keyframes=s)
    for msg in _stream():
        pipe.on_message(msg)
    ahead_det = _Counting()
    ahead = [round(m.stamp, 3) for m, d, _ in _Ahead(_stream(), ahead_det, every, keyframes=s)
             if isinstance(m, CameraFrame) and d is not None]
    assert ahead == in_loop.stamps == sorted(ahead_det.stamps)
    # standing: one image per 0.5 s; driving at 0.25 m/s: one per 10 cm (0.4 s), far fewer than 40
    assert 6 <= len(ahead) <= 14
    assert pipe.keyframes.held == -(-40 // every) - len(ahead)  # the gate sees every every-th image
    assert pipe.images == 40 and pipe.detected_images == len(in_loop.stamps)


def test_bad_keyframe_settings_are_refused():
    from stack.config import ConfigError, resolve_config

    with pytest.raises(ConfigError, match="keyframe_m"):
        resolve_config(sets=["detector.keyframe_m=-0.1"])
    c = resolve_config(sets=["detector.keyframe_m=0.1"])
    assert c.detector.keyframes() == KeyframeSettings(0.1, 0.0, 1.0)
    assert resolve_config().detector.keyframes() is None


def test_the_interval_holds_for_stamps_read_back_from_nanoseconds():
    """A bag stores stamps in nanoseconds: 15.0 s and 16.0 s can come back a nanosecond apart from the
    live floats; the gate looks at the same images either way."""
    for later in (16.0, 16.0 - 1e-9, 16.0 + 1e-9):
        gate = KeyframeGate(KeyframeSettings(min_motion_m=0.1, max_interval_s=1.0))
        gate.on_wheel_odometry(_odom(0.0))
        assert gate.passes(_frame(15.0 + 1e-9))
        assert gate.passes(_frame(later)), later


@pytest.mark.parametrize("every,settings", [(1, KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0, max_interval_s=0.5)),
                                            (2, KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0, max_interval_s=0.5)),
                                            (3, None)])
def test_the_camera_demand_wants_exactly_the_images_the_detector_ahead_runs_on(every, settings):
    """``dopeslam run`` leaves unrendered the images its detector ahead will not see: the demand, shown
    the messages as the simulator makes them, wants the very images ``_Ahead`` detects."""
    from testbed.run import _Ahead, _CameraDemand

    assert _CameraDemand.useful(every, settings)
    assert not _CameraDemand.useful(1, None) and not _CameraDemand.useful(1, KeyframeSettings())
    demand, wanted = _CameraDemand(every, settings), []
    for msg in _stream():
        if isinstance(msg, CameraFrame):
            if demand.wants(msg.stamp):
                wanted.append(round(msg.stamp, 3))
        else:
            demand.see(msg)
    det = _Counting()
    ahead = [round(m.stamp, 3) for m, d, _ in _Ahead(_stream(), det, every, keyframes=settings)
             if isinstance(m, CameraFrame) and d is not None]
    assert wanted == ahead and len(ahead) < 40


def test_the_detector_ahead_refuses_an_image_it_should_detect_that_was_not_rendered():
    from testbed.run import _Ahead

    def stream():
        yield _frame(0.0)
        frame = _frame(0.1)
        frame.extra["unrendered"] = True
        yield frame

    with pytest.raises(RuntimeError, match="not rendered"):
        list(_Ahead(stream(), _Counting(), 1))
