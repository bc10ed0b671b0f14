"""The live run's detector thread (``testbed.run._Ahead``): messages come out in the simulator's order,
each image with the detections a call in the loop would have given, every ``every``-th image detected."""
import threading

import numpy as np
import pytest

from stack.messages import CameraFrame, CameraInfo, Detection, LidarScan
from testbed.run import _Ahead


class CountingDetector:
    """Detections that name the image they came from, and the threads that ran them."""

    def __init__(self):
        self.threads = set()

    def detect(self, frame):
        self.threads.add(threading.current_thread().name)
        return [Detection("det", frame.stamp, np.eye(4), np.zeros((9, 2)), np.ones(9), 0.0)]


def _messages(n=10):
    info = CameraInfo(width=4, height=3, K=np.eye(3))
    for i in range(n):
        yield LidarScan(stamp=i * 0.1, points=np.zeros((1, 3)), times_s=np.zeros(1))
        yield CameraFrame(stamp=i * 0.1 + 0.05, info=info, rgb=np.zeros((3, 4, 3), np.uint8))


@pytest.mark.parametrize("every", [1, 3])
def test_order_and_detections_as_in_the_loop(every):
    det = CountingDetector()
    out = list(_Ahead(_messages(), det, every, images_ahead=2))
    assert [type(m).__name__ for m, _, _ in out] == [type(m).__name__ for m in _messages()]
    images = [(m, d) for m, d, _ in out if isinstance(m, CameraFrame)]
    for i, (m, d) in enumerate(images):
        assert (d if d is None else [(x.cls, x.stamp) for x in d]) == ([("det", m.stamp)] if i % every == 0 else None)
    assert all(d is None for m, d, _ in out if not isinstance(m, CameraFrame))
    assert det.threads and all(t.startswith("run-detection") for t in det.threads)


def test_an_error_in_the_detector_reaches_the_loop():
    class Broken:
        def detect(self, frame):
            raise RuntimeError("weights gone")

    with pytest.raises(RuntimeError, match="weights gone"):
        list(_Ahead(_messages(), Broken()))


class BoundDetector:
    def bind_episode(self, ep):
        pass

    def detect(self, frame):
        return []


@pytest.mark.parametrize("env, sequential, detector, images, expected", [
    (None, False, None, None, (True, True)),  # ahead: the camera renders in a second process
    (None, False, None, 601, (True, True)),
    (None, False, None, 150, (True, True)),
    (None, False, None, 149, (True, False)),  # ... unless the episode is too short to pay its start-up
    (None, False, None, 0, (True, False)),
    (None, True, None, 601, (False, False)),  # in the loop: rendered in the loop too
    (None, False, BoundDetector(), 601, (False, False)),  # a detector bound to the episode runs in the loop
    ("0", False, None, 601, (True, False)),  # the variable, when set, wins
    ("1", True, None, 601, (False, True)),
    ("1", False, None, 10, (True, True)),
])
def test_ahead_settings(monkeypatch, env, sequential, detector, images, expected):
    from testbed.run import ahead_settings

    if env is None:
        monkeypatch.delenv("DOPESLAM_RENDER_WORKER", raising=False)
    else:
        monkeypatch.setenv("DOPESLAM_RENDER_WORKER", env)
    assert ahead_settings(sequential, detector, images) == expected


@pytest.mark.parametrize("duration, rate, expected", [(60.0, 10.0, 601), (13.0, 10.0, 131), (0.0, 10.0, 1),
                                                      (14.9, 10.0, 150), (1.0, 30.0, 31), (-1.0, 10.0, None),
                                                      (float("nan"), 10.0, None), (float("inf"), 10.0, None),
                                                      (10.0, "fast", None), (None, 10.0, None)])
def test_episode_images(duration, rate, expected):
    from testbed.run import episode_images

    assert episode_images(duration, rate) == expected


@pytest.mark.parametrize("value, expected", [(None, True), ("1", True), ("0", False), (" 0 ", False)])
def test_detection_process_setting(value, expected):
    from testbed.settings import detection_process_wanted

    assert detection_process_wanted({} if value is None else {"DOPESLAM_DETECTOR_PROCESS": value}) is expected


@pytest.mark.parametrize("value, expected", [(None, None), ("", None), ("1", 1), (" 2 ", 2), ("0", None),
                                             ("3", None), ("yes", None)])
def test_detector_processes_setting(value, expected):
    from testbed.settings import detector_processes_setting

    assert detector_processes_setting({} if value is None else {"DOPESLAM_DETECTOR_PROCESS": value}) == expected


@pytest.mark.parametrize("value", [None, "1", "2", "0", "yes"])
def test_live_run_detector_processes(monkeypatch, value):
    """Unset, ``dopeslam run`` starts two detector processes where every image is detected (the
    network is the longest path) in an episode of 150 images or more, and one where some go
    undetected or the episode is shorter; ``1`` or ``2`` says how many."""
    from stack.keyframes import KeyframeSettings
    from testbed.run import detector_processes_wanted

    if value is None:
        monkeypatch.delenv("DOPESLAM_DETECTOR_PROCESS", raising=False)
    else:
        monkeypatch.setenv("DOPESLAM_DETECTOR_PROCESS", value)
    gate = KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0)
    forced = {"1": 1, "2": 2}.get(value)
    assert detector_processes_wanted() == (forced or 2)
    assert detector_processes_wanted(1, None) == (forced or 2)
    assert detector_processes_wanted(2, None) == (forced or 1)
    assert detector_processes_wanted(1, gate) == (forced or 1)
    # two only where the episode is long enough to pay the second one's start-up
    assert detector_processes_wanted(1, None, 601) == (forced or 2)
    assert detector_processes_wanted(1, None, 150) == (forced or 2)
    assert detector_processes_wanted(1, None, 149) == (forced or 1)
    assert detector_processes_wanted(1, None, 0) == (forced or 1)
    assert detector_processes_wanted(2, None, 601) == (forced or 1)


@pytest.mark.parametrize("value, expected", [(None, None), ("", None), ("yes", None), ("1", True), (" 1 ", True),
                                             ("0", False), (" 0 ", False)])
def test_odometry_process_setting(monkeypatch, value, expected):
    """Unset, KISS-ICP moves to a process of its own only where some images go undetected (with every
    image detected both cores are busy already); ``0`` never, ``1`` whatever the schedule."""
    from types import SimpleNamespace

    from stack.keyframes import KeyframeSettings
    from testbed.progress import watching
    from testbed.run import odometry_process_wanted
    from testbed.settings import odometry_process_wanted as wanted

    assert wanted({} if value is None else {"DOPESLAM_ODOMETRY_PROCESS": value}) is expected
    if value is None:
        monkeypatch.delenv("DOPESLAM_ODOMETRY_PROCESS", raising=False)
    else:
        monkeypatch.setenv("DOPESLAM_ODOMETRY_PROCESS", value)
    gate = KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0)
    for odometry in (None, "kiss-icp"):
        assert odometry_process_wanted(odometry) is (expected is True)  # every image detected
        assert odometry_process_wanted(odometry, 2) is (expected is not False)
        assert odometry_process_wanted(odometry, 1, gate) is (expected is not False)
    for odometry in ("wheel", lambda T: None):
        assert not odometry_process_wanted(odometry, 2)
    with watching(SimpleNamespace(close=lambda: None)):  # a live view reads every sweep's registered points
        assert not odometry_process_wanted(None, 2)


class SweepLog:
    """Stands in for the odometry process: records the order sweeps are handed over and taken."""

    def __init__(self, answer_other=False):
        self.events, self._queue, self._other = [], [], answer_other

    def submit(self, scan):
        self.events.append(("submit", scan.stamp))
        self._queue.append(scan)

    def take(self):
        scan = self._queue.pop(0)
        self.events.append(("take", scan.stamp))
        return LidarScan(scan.stamp, scan.points, scan.times_s) if self._other else scan


def test_each_sweep_is_registered_before_the_pipeline_gets_it_and_only_a_few_wait():
    pulled = []

    def sweeps_only(n=30):  # no camera: nothing but the sweep bound keeps the simulator near the pipeline
        for i in range(n):
            pulled.append(i)
            yield LidarScan(stamp=i * 0.1, points=np.zeros((1, 3)), times_s=np.zeros(1))

    log = SweepLog()
    given = []
    for msg, dets, _ in _Ahead(sweeps_only(), CountingDetector(), odometry=log, scans_ahead=3):
        assert ("take", msg.stamp) in log.events and dets is None
        assert len(pulled) - len(given) <= 4  # at most 3 wait, and the one given now
        given.append(msg.stamp)
    assert given == [i * 0.1 for i in range(30)]
    assert [s for e, s in log.events if e == "submit"] == given == [s for e, s in log.events if e == "take"]
    # with images, sweeps go to the odometry as they come, whatever the detector is doing
    log = SweepLog()
    out = list(_Ahead(_messages(), CountingDetector(), odometry=log))
    assert [m.stamp for m, _, _ in out if isinstance(m, LidarScan)] == [s for e, s in log.events if e == "take"]
    with pytest.raises(RuntimeError, match="answered another"):
        list(_Ahead(_messages(), CountingDetector(), odometry=SweepLog(answer_other=True)))
