"""Retiring labels on negative evidence (``stack.retire``), on hand-built images and message streams:
an object seen, one not seen though its place is in view and empty, one hidden behind something
nearer, one there but missed by the detector; retirement, coming back, hand-edited rows."""
from __future__ import annotations

import numpy as np
import pytest

from stack.messages import CameraFrame, CameraInfo, Detection, LidarScan
from stack.object_store import ObjectStore, Observation
from helpers.loop_closer import RecordingLoopCloser
from stack.pipeline import DopeSlam
from stack.retire import EMPTY, OCCLUDED, OUT_OF_VIEW, PRESENT, RETIRED, RetireConfig, Retirement, classify, retire
from stack.transforms import inv

INFO = CameraInfo.from_fov(160, 120, 120.0)
SIZE = np.array([0.054, 0.068, 0.068])  # a Yogurt
DIMS = {"Yogurt": SIZE}
T_BASE_CAM = np.array([[0.0, 0.0, 1.0, 0.1], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.3], [0, 0, 0, 1.0]])
OBJ = np.array([1.1, 0.0, 0.3])  # 1 m ahead of the camera at the start
WALL_M, NEAR_M = 3.0, 0.5


def depth_image(kind: str, T_map_cam=np.eye(4), xyz=np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """The wall 3 m away; ``present``: the object's front face drawn where it is; ``occluded``:
    something 0.5 m away over the whole image."""
    d = np.full((INFO.height, INFO.width), WALL_M, np.float32)
    if kind == "occluded":
        d[:] = NEAR_M
    elif kind == "present":
        p = inv(T_map_cam)[:3, :3] @ xyz + inv(T_map_cam)[:3, 3]
        u, v = INFO.fx * p[0] / p[2] + INFO.cx, INFO.fy * p[1] / p[2] + INFO.cy
        r = int(0.5 * SIZE[1] * INFO.fx / p[2])
        d[max(0, int(v) - r):int(v) + r + 1, max(0, int(u) - r):int(u) + r + 1] = p[2] - SIZE[0] / 2
    return d


@pytest.mark.parametrize("kind, expected", [("empty", EMPTY), ("present", PRESENT), ("occluded", OCCLUDED)])
def test_classify_what_the_depth_shows(kind, expected):
    cfg = RetireConfig()
    xyz = np.array([0.0, 0.0, 1.0])
    assert classify(xyz, SIZE, np.eye(4), INFO, depth_image(kind), cfg) == expected


def test_classify_out_of_view_and_range():
    cfg = RetireConfig()
    d = depth_image("empty")
    assert classify(np.array([2.0, 0.0, 1.0]), SIZE, np.eye(4), INFO, d, cfg) == OUT_OF_VIEW  # beside the image
    assert classify(np.array([0.0, 0.0, -1.0]), SIZE, np.eye(4), INFO, d, cfg) == OUT_OF_VIEW  # behind
    assert classify(np.array([0.0, 0.0, 4.0]), SIZE, np.eye(4), INFO, d, cfg) == OUT_OF_VIEW  # too far
    no_depth = np.zeros_like(d)
    assert classify(np.array([0.0, 0.0, 1.0]), SIZE, np.eye(4), INFO, no_depth, cfg) == "no_depth"


def _store_with_object(edited: bool = False) -> ObjectStore:
    store = ObjectStore(dims=DIMS, evidence=None)
    for k in range(5):
        obj = store.add(Observation(0.1 * k, "Yogurt", np.array([0.0, 0.0, 1.0]), np.array([0, 0, 0, 1.0])))
    obj.edited = edited
    return store


def test_retired_after_enough_empty_views_and_seen_clears_misses():
    store = _store_with_object()
    r = Retirement(RetireConfig(misses=5, min_span_s=0.3))
    d = depth_image("empty")
    for k in range(4):
        assert r.view(store, np.eye(4), INFO, d, set(), 1.0 + 0.1 * k) == []
    r.view(store, np.eye(4), INFO, depth_image("present"), {1}, 1.4)  # a sighting: misses start again
    for k in range(4):
        assert r.view(store, np.eye(4), INFO, d, set(), 1.5 + 0.1 * k) == []
    assert r.view(store, np.eye(4), INFO, d, set(), 1.9) == [1]
    assert store.objects[1].status == RETIRED and "empty" in store.objects[1].reason
    store.publish()
    assert store.labels() == []


@pytest.mark.parametrize("kind", ["occluded", "present"])
def test_not_retired_when_hidden_or_there(kind):
    store = _store_with_object()
    r = Retirement(RetireConfig(misses=3, min_span_s=0.0))
    for k in range(20):
        r.view(store, np.eye(4), INFO, depth_image(kind), set(), 1.0 + 0.1 * k)
    assert store.objects[1].status != RETIRED


def test_edited_rows_are_never_retired():
    store = _store_with_object(edited=True)
    r = Retirement(RetireConfig(misses=2, min_span_s=0.0))
    for k in range(10):
        r.view(store, np.eye(4), INFO, depth_image("empty"), set(), 1.0 + 0.1 * k)
    assert store.objects[1].status != RETIRED


def test_a_retired_object_seen_again_comes_back_where_it_is_now():
    store = _store_with_object()
    obj = store.objects[1]
    retire(obj, "test", revive_after=3)
    seen = [Observation(5.0 + 0.1 * k, "Yogurt", np.array([0.2, 0.0, 1.0]), np.array([0, 0, 0, 1.0]))
            for k in range(3)]
    for o in seen[:2]:  # fewer sightings than revive_after: still retired, nothing of them in its label
        assert store.add(o) is obj and obj.status == RETIRED and obj.history and len(obj.sightings) <= 2
    back = store.add(seen[2])
    assert back is obj and obj.status != RETIRED and obj.sightings == []
    assert len(obj.history) == 3 and len(obj.past) == 5
    assert np.allclose(obj.xyz, [0.2, 0.0, 1.0])  # labelled from what is seen now, not the old place
    store.publish()
    assert obj.is_label


def test_stray_sightings_of_a_retired_object_are_cleared_by_its_empty_place():
    store = _store_with_object()
    obj = store.objects[1]
    retire(obj, "test", revive_after=3)
    stray = Observation(5.0, "Yogurt", obj.xyz.copy(), np.array([0, 0, 0, 1.0]))
    store.add(stray)
    store.add(stray)
    assert obj.status == RETIRED and len(obj.sightings) == 2
    Retirement(RetireConfig()).view(store, np.eye(4), INFO, depth_image("empty"), [], 6.0)
    assert obj.sightings == []  # the place was seen empty since: the strays do not add up
    store.add(stray)
    assert obj.status == RETIRED


def test_detections_fpr_rejected_do_not_bring_a_retired_object_back():
    store = _store_with_object()
    obj = store.objects[1]
    retire(obj, "test", revive_after=3)
    rejected = Observation(5.0, "Yogurt", obj.xyz.copy(), np.array([0, 0, 0, 1.0]), fpr_pass=False)
    for _ in range(5):
        assert store.add(rejected) is obj
    assert obj.status == RETIRED and obj.sightings == []


# --- through the pipeline -----------------------------------------------------------------------

class SlideOdometry:
    """``base_link`` sliding along map y at 0.2 m/s (the viewpoints differ), a pose per sweep."""

    def __init__(self):
        self.stamps: list[float] = []

    @staticmethod
    def pose(t):
        T = np.eye(4)
        T[1, 3] = 0.2 * t
        return T

    def process(self, scan):
        self.stamps.append(scan.stamp)
        return self.pose(scan.stamp)

    def pose_at(self, t):
        if not self.stamps or t < self.stamps[0] or t > self.stamps[-1]:
            return None
        return self.pose(t)

    def trajectory(self):
        return np.array(self.stamps), np.array([self.pose(t) for t in self.stamps]).reshape(-1, 4, 4)


class Scripted:
    """Sees the Yogurt (its true pose in the camera) while ``visible(t)``."""

    def __init__(self, visible):
        self.visible = visible

    def detect(self, frame):
        if not self.visible(frame.stamp):
            return []
        T_map_obj = np.eye(4)
        T_map_obj[:3, 3] = OBJ
        T_cam_obj = inv(SlideOdometry.pose(frame.stamp) @ T_BASE_CAM) @ T_map_obj
        return [Detection("Yogurt", frame.stamp, T_cam_obj, np.zeros((9, 2)), np.ones(9), 1.0)]


def _run(visible, depth_kind, seconds=3.0, retire=RetireConfig()) -> DopeSlam:
    pipe = DopeSlam(SlideOdometry(), Scripted(visible), T_BASE_CAM, DIMS, retire=retire)
    for k in range(int(seconds * 10) + 1):
        t = 0.1 * k
        T_map_cam = SlideOdometry.pose(t) @ T_BASE_CAM
        kind = "present" if visible(t) else depth_kind
        pipe.on_image(CameraFrame(t, INFO, None, depth_image(kind, T_map_cam, OBJ)))
        pipe.on_scan(LidarScan(t + 0.05, np.zeros((0, 3)), np.zeros(0)))
    pipe.finish()
    return pipe


def test_pipeline_retires_a_label_whose_place_is_seen_empty():
    pipe = _run(lambda t: t < 1.5, "empty")
    (obj,) = list(pipe.store)
    assert obj.status == RETIRED and pipe.store.labels() == []
    assert pipe.retirement.summary()["retired"][0]["id"] == obj.id


@pytest.mark.parametrize("kind", ["occluded", "present"])
def test_pipeline_keeps_a_label_hidden_or_missed(kind):
    pipe = _run(lambda t: t < 1.5, kind)
    assert [o.status for o in pipe.store] == ["label"]


def test_pipeline_without_retirement_keeps_the_stale_label():
    pipe = _run(lambda t: t < 1.5, "empty", retire=None)
    assert [o.status for o in pipe.store] == ["label"]


def test_pipeline_object_back_after_retirement():
    pipe = _run(lambda t: t < 1.2 or t > 3.0, "empty", seconds=5.0)
    (obj,) = list(pipe.store)
    assert obj.is_label and obj.past and np.allclose(obj.xyz, OBJ, atol=1e-6)


SHIFT_X = np.array([[1.0, 0, 0, 0.05], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # the 'loop closure'


def _run_closing(visible, seconds):
    pipe = DopeSlam(SlideOdometry(), Scripted(visible), T_BASE_CAM, DIMS, retire=RetireConfig(),
                    loop_closer=RecordingLoopCloser(SHIFT_X))
    for k in range(int(seconds * 10) + 1):
        t = 0.1 * k
        T_map_cam = SlideOdometry.pose(t) @ T_BASE_CAM
        pipe.on_image(CameraFrame(t, INFO, None, depth_image("present" if visible(t) else "empty", T_map_cam, OBJ)))
        pipe.on_scan(LidarScan(t + 0.05, np.zeros((0, 3)), np.zeros(0)))
    pipe.finish()
    return pipe


def test_a_retired_label_stays_retired_when_loop_closure_fuses_the_map_again():
    pipe = _run_closing(lambda t: t < 1.5, 3.0)
    (obj,) = list(pipe.store)  # the store fused anew on the corrected trajectory
    assert obj.status == RETIRED and pipe.store.labels() == [] and "empty" in obj.reason
    assert np.allclose(obj.xyz, OBJ + [0.05, 0, 0], atol=1e-6)  # placed with the correction


def test_an_object_back_after_retirement_is_a_label_after_loop_closure_too():
    pipe = _run_closing(lambda t: t < 1.2 or t > 3.0, 5.0)
    (obj,) = list(pipe.store)
    assert obj.is_label


def test_detections_fpr_rejected_at_an_emptied_place_do_not_keep_its_label():
    """Only FPR-passing detections are sightings: rejected ones near the place (here every image once it
    is empty) do not clear its misses, so the label whose object is gone is still retired."""
    class RejectedLater(Scripted):
        def detect(self, frame):
            dets = super().detect(frame) if frame.stamp < 1.5 else Scripted(lambda t: True).detect(frame)
            for d in dets:
                d.fpr_pass = frame.stamp < 1.5
            return dets

    pipe = DopeSlam(SlideOdometry(), RejectedLater(lambda t: True), T_BASE_CAM, DIMS, retire=RetireConfig())
    for k in range(31):
        t = 0.1 * k
        T_map_cam = SlideOdometry.pose(t) @ T_BASE_CAM
        pipe.on_image(CameraFrame(t, INFO, None, depth_image("present" if t < 1.5 else "empty", T_map_cam, OBJ)))
        pipe.on_scan(LidarScan(t + 0.05, np.zeros((0, 3)), np.zeros(0)))
    pipe.finish()
    (obj,) = list(pipe.store)
    assert obj.status == RETIRED
