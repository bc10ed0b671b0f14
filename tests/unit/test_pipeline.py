"""The pipeline (``stack.pipeline.DopeSlam``) on hand-built message streams: when an image's detections
are fused (once the odometry has a pose after the image), with which pose (interpolated at the image's
stamp), what ``finish`` does with the images still waiting, and the hooks a loop closer rides on.

The odometry and detector are test doubles: a robot driving along map x at 1 m/s, a detector that
sees one Yogurt 1 m ahead of the camera in every image.
"""
from __future__ import annotations

import numpy as np
import pytest

from stack.messages import CameraFrame, CameraInfo, Detection, LidarScan, WheelOdometry
from stack.object_store import ObjectStore
from helpers.loop_closer import RecordingLoopCloser
from stack.pipeline import MAP_EVERY, MAP_POINT_STRIDE, DopeSlam
from stack.transforms import inv

DIMS = {"Yogurt": (0.054, 0.068, 0.068), "Mustard": (0.16, 0.049, 0.065)}
SPEED = 1.0  # m/s along map x
SWEEP_MID_S = 0.05  # the odometry's pose is at the middle of the sweep
FLOOR = (np.array([0.0, 0.0, 1.0]), 0.0)
T_BASE_CAM = np.array([[0.0, 0.0, 1.0, 0.1],  # optical frame: z forward (base x), x right, y down
                       [-1.0, 0.0, 0.0, 0.0],
                       [0.0, -1.0, 0.0, 0.3],
                       [0.0, 0.0, 0.0, 1.0]])
T_CAM_OBJ = np.eye(4)
T_CAM_OBJ[2, 3] = 1.0  # 1 m ahead of the camera


def pose_x(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


class LineOdometry:
    """``base_link`` at x = SPEED * t; a pose at each sweep's middle; linear interpolation between
    poses, ``extrapolation_s`` past the last one, nothing before the first."""

    def __init__(self, extrapolation_s: float = 0.0, skip: tuple[float, ...] = ()):
        self.stamps: list[float] = []
        self.extrapolation_s = extrapolation_s
        self.skip = skip
        self.last_points_base = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])

    def process(self, scan: LidarScan):
        if scan.stamp in self.skip:
            return None
        self.stamps.append(scan.stamp + SWEEP_MID_S)
        return pose_x(SPEED * self.stamps[-1])

    def pose_at(self, t: float):
        if not self.stamps or t < self.stamps[0] or t > self.stamps[-1] + self.extrapolation_s:
            return None
        return pose_x(SPEED * t)

    def trajectory(self):
        return np.array(self.stamps), np.array([pose_x(SPEED * t) for t in self.stamps]).reshape(-1, 4, 4)

    def floor_plane_map(self):
        return FLOOR


class YogurtAhead:
    def __init__(self):
        self.seen: list[float] = []

    def detect(self, frame: CameraFrame) -> list[Detection]:
        self.seen.append(frame.stamp)
        return [Detection("Yogurt", frame.stamp, T_CAM_OBJ.copy(), np.zeros((9, 2)), np.ones(9), 1.0)]


INFO = CameraInfo.from_fov(4, 3, 2.0)


def scan(t: float) -> LidarScan:
    return LidarScan(t, np.zeros((0, 3)), np.zeros(0))


def image(t: float) -> CameraFrame:
    return CameraFrame(t, INFO)


def expected_xyz(t_image: float) -> np.ndarray:
    """Where the Yogurt lands when fused with the robot pose at ``t_image``."""
    return (pose_x(SPEED * t_image) @ T_BASE_CAM @ T_CAM_OBJ)[:3, 3]


def make(odometry=None, detector=None, **kw) -> DopeSlam:
    return DopeSlam(odometry or LineOdometry(), detector or YogurtAhead(), T_BASE_CAM, DIMS, **kw)


def observations(pipe: DopeSlam):
    return [o for m in pipe.store for o in m.history]


def test_an_image_waits_for_a_pose_after_its_stamp_and_is_fused_with_the_interpolated_pose():
    pipe = make()
    pipe.on_scan(scan(0.0))  # pose at 0.05
    dets = pipe.on_image(image(0.12))
    assert len(dets) == 1 and dets[0].stamp == 0.12  # the harness gets the detections to score
    assert len(pipe.store) == 0  # 0.12 is after the newest pose: it waits
    pipe.on_wheel_odometry(WheelOdometry(0.13, np.eye(4), 0.0, 0.0))
    assert len(pipe.store) == 0  # wheel odometry gives the map no pose
    pipe.on_scan(scan(0.1))  # pose at 0.15 > 0.12
    (obs,) = observations(pipe)
    np.testing.assert_allclose(obs.xyz, expected_xyz(0.12), atol=1e-12)
    np.testing.assert_allclose(obs.cam_xyz, (pose_x(0.12) @ T_BASE_CAM)[:3, 3], atol=1e-12)
    assert obs.stamp == 0.12 and obs.range_m == pytest.approx(1.0)


def test_an_image_at_a_pose_stamp_is_fused_at_that_scan():
    pipe = make()
    pipe.on_scan(scan(0.0))
    pipe.on_image(image(0.05))
    assert len(pipe.store) == 0  # fusion happens when the next scan arrives ...
    pipe.on_scan(scan(0.1))
    assert len(observations(pipe)) == 1  # ... and then 0.05 <= the newest pose: fused


def test_images_in_the_order_they_came_each_when_its_pose_exists():
    pipe = make()
    pipe.on_scan(scan(0.0))  # pose 0.05
    for t in (0.06, 0.1, 0.16):
        pipe.on_image(image(t))
    pipe.on_scan(scan(0.1))  # pose 0.15: the first two
    assert [o.stamp for o in observations(pipe)] == [0.06, 0.1]
    pipe.on_scan(scan(0.2))  # pose 0.25: the third
    assert [o.stamp for o in observations(pipe)] == [0.06, 0.1, 0.16]


def test_a_skipped_scan_gives_no_pose_and_fuses_nothing_new():
    odom = LineOdometry(skip=(0.1,))
    pipe = make(odom)
    pipe.on_scan(scan(0.0))
    pipe.on_image(image(0.1))
    assert pipe.on_scan(scan(0.1)) is None and len(pipe.store) == 0
    assert pipe.on_scan(scan(0.2)) is not None and len(observations(pipe)) == 1


def test_images_before_the_first_pose_are_dropped_when_the_odometry_has_none_there():
    pipe = make()
    pipe.on_image(image(0.0))
    pipe.on_image(image(0.02))
    pipe.on_scan(scan(0.0))  # pose at 0.05; the double knows nothing before it
    assert len(pipe.store) == 0 and pipe.unposed == 2
    res = pipe.finish()
    assert res.unposed == 2


def test_finish_fuses_the_waiting_images_where_a_pose_is_known_and_drops_the_rest():
    pipe = make(LineOdometry(extrapolation_s=0.03))
    pipe.on_scan(scan(0.0))  # pose 0.05
    pipe.on_image(image(0.07))  # within the extrapolation
    pipe.on_image(image(0.2))  # beyond it
    assert len(pipe.store) == 0
    res = pipe.finish()
    assert [o.stamp for o in observations(pipe)] == [0.07] and res.unposed == 1
    np.testing.assert_allclose(observations(pipe)[0].xyz, expected_xyz(0.07), atol=1e-12)


def test_finish_sets_the_floor_from_the_odometry_publishes_and_returns_the_trajectory():
    pipe = make(keep_observations=True)
    for k in range(4):
        pipe.on_scan(scan(0.1 * k))
        pipe.on_image(image(0.1 * k + 0.02))
        pipe.on_wheel_odometry(WheelOdometry(0.1 * k, pose_x(0.1 * k), 1.0, 0.0))
    res = pipe.finish()
    assert res.store is pipe.store and res.store.floor is FLOOR
    (obj,) = res.store
    # published: a few observations from one line of sight are not enough evidence for a label
    assert obj.status == "candidate" and obj.reason
    np.testing.assert_allclose(res.stamps, [0.05, 0.15, 0.25, 0.35])
    np.testing.assert_allclose(res.T_map_base[:, 0, 3], res.stamps)
    assert res.T_map_base_odometry is res.T_map_base  # no loop closer
    np.testing.assert_allclose(res.wheel_stamps, [0.0, 0.1, 0.2, 0.3])
    # the image at 0.02 came before the first pose (0.05): dropped; 0.32 is fused at the last scan
    assert [o.stamp for o in res.observations] == pytest.approx([0.12, 0.22, 0.32]) and res.unposed == 1
    with pytest.raises(RuntimeError, match="already"):
        pipe.finish()


def test_an_odometry_without_a_floor_leaves_the_store_without_one():
    class NoFloor(LineOdometry):
        floor_plane_map = None

    pipe = make(NoFloor())
    pipe.on_scan(scan(0.0))
    assert pipe.finish().store.floor is None


def test_detect_every_runs_the_detector_on_every_nth_image_only():
    det = YogurtAhead()
    pipe = make(detector=det, detect_every=3)
    results = [pipe.on_image(image(0.01 * k)) for k in range(7)]
    assert det.seen == [0.0, 0.03, 0.06] and [r is None for r in results] == [False, True, True] * 2 + [False]
    assert pipe.images == 7 and pipe.detected_images == 3


def test_the_lidar_map_keeps_every_fifth_registered_sweep():
    pipe = make()
    for k in range(2 * MAP_EVERY + 1):
        pipe.on_scan(scan(0.1 * k))
    pts = pipe.finish().map_points
    assert len(pts) == 3  # registered sweeps 1, 6, 11
    np.testing.assert_allclose(pts[1][0], [1.0 + 0.55, 0.0, 0.0])  # sweep 6's pose at t = 0.55


def test_a_long_run_thins_its_lidar_map_to_one_point_per_voxel(monkeypatch):
    """Past MAP_POINT_LIMIT points the map is one point per voxel: its memory follows the place, not
    the time (a robot going back and forth adds nothing); the points kept are points of the map."""
    import stack.pipeline as sp

    class Standing(LineOdometry):  # the robot stands still: every sweep sees the same place
        def process(self, scan):
            self.stamps.append(scan.stamp)
            return np.eye(4)

    monkeypatch.setattr(sp, "MAP_POINT_LIMIT", 4000)
    odo = Standing()
    centres = (np.arange(40) + 0.5) * sp.MAP_VOXEL_M
    grid = np.stack(np.meshgrid(centres, centres, [0.5 + 0.5 * sp.MAP_VOXEL_M]), -1).reshape(-1, 3)
    odo.last_points_base = np.repeat(grid, MAP_POINT_STRIDE, axis=0)  # 1600 points kept per sweep
    pipe = DopeSlam(odo, None, T_BASE_CAM, DIMS)
    for k in range(MAP_EVERY * 40):
        pipe.on_scan(scan(0.1 * k))
    assert pipe.map_compactions >= 1
    pts = np.concatenate(pipe.map_points)
    assert len(pts) <= 4000 and len(pts) >= 1600
    keys = {tuple(v) for v in np.floor(pts / sp.MAP_VOXEL_M).astype(int)}
    assert len(keys) == 1600  # the place is still all there


def test_messages_dispatch_by_type():
    pipe = make()
    assert pipe.on_message(scan(0.0)) is not None
    assert len(pipe.on_message(image(0.01))) == 1
    pipe.on_message(WheelOdometry(0.0, np.eye(4), 0.0, 0.0))
    with pytest.raises(TypeError, match="LidarScan"):
        pipe.on_message("not a message")


def test_a_detector_without_detect_is_refused():
    with pytest.raises(TypeError, match="detect"):
        DopeSlam(LineOdometry(), object(), T_BASE_CAM, DIMS)


def test_a_loop_closer_rides_along_and_its_corrected_trajectory_places_the_map_again():
    lc = RecordingLoopCloser()
    pipe = make(loop_closer=lc, detect_every=2)
    pipe.on_scan(scan(0.0))
    pipe.on_image(image(0.07))
    pipe.on_image(image(0.09))  # not detected, but the loop closer still sees it (key frames)
    pipe.on_scan(scan(0.1))
    res = pipe.finish()
    assert lc.scans == [pytest.approx(0.05), pytest.approx(0.15)] and lc.images == [0.07, 0.09]
    assert [d.stamp for d in lc.fused] == [0.07]
    assert isinstance(res.store, ObjectStore) and res.store is pipe.store and res.store.floor is FLOOR
    (obj,) = res.store
    np.testing.assert_allclose(obj.xyz, expected_xyz(0.07) + [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(res.T_map_base[:, 1, 3], 1.0)
    np.testing.assert_allclose(res.T_map_base_odometry[:, 1, 3], 0.0)
    assert len(res.map_points) == 1


def test_the_fused_pose_is_the_chain_map_base_camera_object():
    """T_map_obj = T_map_base(t) @ T_base_cam @ T_cam_obj, also for a turned robot (not only along x)."""

    class Turned(LineOdometry):
        def pose_at(self, t):
            T = super().pose_at(t)
            if T is None:
                return None
            c, s = np.cos(t), np.sin(t)
            T[:2, :2] = [[c, -s], [s, c]]
            return T

    pipe = make(Turned())
    pipe.on_scan(scan(0.0))
    pipe.on_image(image(0.1))
    pipe.on_scan(scan(0.1))
    (obs,) = observations(pipe)
    c, s = np.cos(0.1), np.sin(0.1)
    T_map_base = np.array([[c, -s, 0, 0.1], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.testing.assert_allclose(obs.xyz, (T_map_base @ T_BASE_CAM @ T_CAM_OBJ)[:3, 3], atol=1e-12)
    # the camera sits where the mounting puts it: 0.1 m ahead of base_link, 0.3 m up
    np.testing.assert_allclose(inv(T_map_base)[:3, :3] @ obs.cam_xyz + inv(T_map_base)[:3, 3], [0.1, 0, 0.3],
                               atol=1e-12)


# --- what a harness that labels on its own, or detects elsewhere, gets --------------------------------

def test_each_detected_image_is_handed_over_once_fused_in_order_with_its_pose():
    fused = []
    pipe = make(LineOdometry(extrapolation_s=0.03), on_fused_image=fused.append)
    pipe.on_image(image(0.0))  # before any pose: handed over unposed
    pipe.on_scan(scan(0.0))  # pose 0.05
    assert [f.stamp for f in fused] == [0.0] and fused[0].T_map_base is None and fused[0].observations == [None]
    pipe.on_image(image(0.08))
    pipe.on_image(image(0.12))
    assert len(fused) == 1  # both wait for a pose after them
    pipe.on_scan(scan(0.1))  # pose 0.15
    pipe.on_image(image(0.17))
    pipe.on_image(image(0.4))  # past the last pose + extrapolation at the end
    pipe.finish()
    assert [f.index for f in fused] == [0, 1, 2, 3, 4] and [f.stamp for f in fused] == [0.0, 0.08, 0.12, 0.17, 0.4]
    for f in fused[1:4]:
        np.testing.assert_allclose(f.T_map_base, pose_x(f.stamp), atol=1e-12)
        (obs,) = f.observations
        np.testing.assert_allclose(obs.xyz, expected_xyz(f.stamp), atol=1e-12)
        assert f.detections[0].stamp == f.stamp
    assert fused[4].T_map_base is None and fused[4].observations == [None] and pipe.unposed == 2


def test_detections_found_elsewhere_are_fused_with_the_same_rule_and_no_detector_runs():
    det = YogurtAhead()
    pipe = make(detector=det, detect_every=5)
    pipe.on_scan(scan(0.0))
    given = [Detection("Mustard", 0.09, T_CAM_OBJ.copy(), np.zeros((9, 2)), np.ones(9), 3.0)]
    assert pipe.on_image(image(0.09), given) == given
    assert pipe.on_image(image(0.095), []) == []  # detected, nothing found
    assert det.seen == [] and pipe.images == 2 and pipe.detected_images == 2
    assert len(pipe.store) == 0
    pipe.on_scan(scan(0.1))
    (obs,) = observations(pipe)
    assert obs.cls == "Mustard"
    np.testing.assert_allclose(obs.xyz, expected_xyz(0.09), atol=1e-12)


def test_without_a_detector_images_only_reach_the_loop_closer():
    lc = RecordingLoopCloser()
    pipe = DopeSlam(LineOdometry(), None, T_BASE_CAM, DIMS, loop_closer=lc)
    pipe.on_scan(scan(0.0))
    assert pipe.on_image(image(0.07)) is None
    pipe.on_scan(scan(0.1))
    res = pipe.finish()
    assert lc.images == [0.07] and pipe.images == 1 and pipe.detected_images == 0 and len(res.store) == 0
    np.testing.assert_allclose(res.T_map_base[:, 1, 3], 1.0)  # the loop closer still corrects the trajectory


def test_map_objects_false_fuses_and_hands_over_but_keeps_the_store_empty():
    fused = []
    pipe = make(on_fused_image=fused.append, map_objects=False, keep_observations=True)
    pipe.on_scan(scan(0.0))
    pipe.on_image(image(0.1))
    pipe.on_scan(scan(0.1))
    res = pipe.finish()
    assert len(res.store) == 0 and len(fused) == 1 and len(res.observations) == 1
    np.testing.assert_allclose(fused[0].observations[0].xyz, expected_xyz(0.1), atol=1e-12)


def test_wheel_odometry_reaches_an_odometry_that_takes_it():
    class WheelHungry(LineOdometry):
        def __init__(self):
            super().__init__()
            self.wheel = []

        def on_wheel_odometry(self, msg):
            self.wheel.append(msg.stamp)

    odom = WheelHungry()
    pipe = make(odom)
    for t in (0.0, 0.02, 0.04):
        pipe.on_message(WheelOdometry(t, pose_x(t), 1.0, 0.0))
    assert odom.wheel == [0.0, 0.02, 0.04] and len(pipe.wheel) == 3


def test_an_odometry_without_the_protocol_methods_is_refused():
    class NoTrajectory:
        def process(self, scan):
            return None

        def pose_at(self, t):
            return None

    with pytest.raises(TypeError, match="odometry NoTrajectory"):
        DopeSlam(NoTrajectory(), YogurtAhead(), T_BASE_CAM, DIMS)
