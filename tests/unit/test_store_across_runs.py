"""The object store across two runs (``dopeslam run --store PATH``), on hand-built message streams
through the real pipeline: run 1 maps two objects and saves the store; a person edits a row; run 2
starts from the saved file in a rearranged room: the moved object's old row is retired and it is
labelled at its new place, the object that stayed keeps its row, the edited row stays as it was
left, a new object is added."""
from __future__ import annotations

import numpy as np
import openpyxl
import pytest

from stack.messages import CameraFrame, CameraInfo, Detection, LidarScan
from stack.object_store import ObjectStore
from stack.pipeline import DopeSlam
from stack.retire import RETIRED, RetireConfig
from stack.transforms import inv

INFO = CameraInfo.from_fov(160, 120, 120.0)
DIMS = {"Yogurt": (0.054, 0.068, 0.068), "Mustard": (0.16, 0.049, 0.065), "Cookies": (0.167, 0.04, 0.123)}
T_BASE_CAM = np.array([[0.0, 0.0, 1.0, 0.1], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.3], [0, 0, 0, 1.0]])
WALL_M = 4.0


class Slide:
    """``base_link`` sliding along map y at 0.2 m/s, starting at y = -0.3 (the same start each run)."""

    def __init__(self):
        self.stamps = []

    @staticmethod
    def pose(t):
        T = np.eye(4)
        T[1, 3] = -0.3 + 0.2 * t
        return T

    def process(self, scan):
        self.stamps.append(scan.stamp)
        return self.pose(scan.stamp)

    def pose_at(self, t):
        return self.pose(t) if self.stamps and self.stamps[0] <= t <= self.stamps[-1] else None

    def trajectory(self):
        return np.array(self.stamps), np.array([self.pose(t) for t in self.stamps]).reshape(-1, 4, 4)


class World:
    """Objects (class -> map position); the detector sees each one in view; the depth image shows
    each one's front face and the wall behind."""

    def __init__(self, objects: dict[str, np.ndarray]):
        self.objects = objects

    def detect(self, frame):
        out = []
        T_cam_map = inv(Slide.pose(frame.stamp) @ T_BASE_CAM)
        for cls, xyz in self.objects.items():
            T = np.eye(4)
            T[:3, 3] = xyz
            T_cam_obj = T_cam_map @ T
            z = T_cam_obj[2, 3]
            u = INFO.fx * T_cam_obj[0, 3] / z + INFO.cx
            if z > 0.3 and 10 < u < INFO.width - 10:
                out.append(Detection(cls, frame.stamp, T_cam_obj, np.zeros((9, 2)), np.ones(9), 1.0))
        return out

    def depth(self, t):
        d = np.full((INFO.height, INFO.width), WALL_M, np.float32)
        T_cam_map = inv(Slide.pose(t) @ T_BASE_CAM)
        for cls, xyz in self.objects.items():
            p = T_cam_map[:3, :3] @ xyz + T_cam_map[:3, 3]
            u, v = INFO.fx * p[0] / p[2] + INFO.cx, INFO.fy * p[1] / p[2] + INFO.cy
            r = int(0.03 * INFO.fx / p[2])
            d[max(0, int(v) - r):int(v) + r + 1, max(0, int(u) - r):int(u) + r + 1] = p[2] - 0.02
        return d


def drive(world: World, store_path=None, seconds=3.0) -> ObjectStore:
    pipe = DopeSlam(Slide(), world, T_BASE_CAM, DIMS, retire=RetireConfig())
    if store_path is not None and store_path.exists():
        pipe.store = ObjectStore.load(store_path, dims=DIMS)
    for k in range(int(seconds * 10) + 1):
        t = 0.1 * k
        pipe.on_image(CameraFrame(t, INFO, None, world.depth(t)))
        pipe.on_scan(LidarScan(t + 0.05, np.zeros((0, 3)), np.zeros(0)))
    return pipe.finish().store


def _edit_xlsx_row(path, cls: str, dx: float) -> None:
    wb = openpyxl.load_workbook(path)
    ws = wb.active
    header = [c.value for c in ws[1]]
    for row in ws.iter_rows(min_row=2):
        if row[header.index("class")].value == cls:
            row[header.index("x")].value += dx
            row[header.index("edited")].value = True
    wb.save(path)


@pytest.mark.parametrize("suffix", [".json", ".xlsx"])
def test_store_across_two_runs(tmp_path, suffix):
    path = tmp_path / f"labels{suffix}"
    day1 = {"Yogurt": np.array([1.1, 0.0, 0.3]), "Mustard": np.array([1.2, 0.25, 0.3]),
            "Cookies": np.array([1.3, -0.2, 0.3])}
    store1 = drive(World(day1))
    assert sorted(o.cls for o in store1.labels()) == ["Cookies", "Mustard", "Yogurt"]
    store1.save(path)
    ids1 = {o.cls: o.id for o in store1}
    if suffix == ".xlsx":
        _edit_xlsx_row(path, "Cookies", 0.05)
    else:  # edit the JSON row as a person would in a text editor
        import json

        doc = json.loads(path.read_text())
        row = next(r for r in doc["objects"] if r["class"] == "Cookies")
        row["x"] += 0.05
        row["edited"] = True
        path.write_text(json.dumps(doc))
    edited_x = next(o for o in ObjectStore.load(path, dims=DIMS) if o.cls == "Cookies").xyz[0]

    # day 2: the Yogurt moved 0.8 m, the Mustard stayed, the Cookies are where they were
    day2 = {"Yogurt": np.array([1.1, 0.8, 0.3]), "Mustard": day1["Mustard"], "Cookies": day1["Cookies"]}
    store2 = drive(World(day2), path, seconds=5.0)
    store2.save(path)
    back = {o.id: o for o in ObjectStore.load(path, dims=DIMS)}
    old_yogurt = back[ids1["Yogurt"]]
    assert old_yogurt.status == RETIRED  # its place was seen empty
    new_yogurt = [o for o in back.values() if o.cls == "Yogurt" and o.id not in ids1.values()]
    assert len(new_yogurt) == 1 and new_yogurt[0].is_label
    assert np.linalg.norm(new_yogurt[0].xyz - day2["Yogurt"]) < 0.01
    mustard = back[ids1["Mustard"]]
    assert mustard.is_label and np.linalg.norm(mustard.xyz - day1["Mustard"]) < 0.01
    cookies = back[ids1["Cookies"]]
    assert cookies.edited and cookies.xyz[0] == pytest.approx(edited_x)  # as the person left it
    assert len(back) == 4


def test_without_retirement_the_old_row_stays_a_label(tmp_path):
    path = tmp_path / "labels.json"
    drive(World({"Yogurt": np.array([1.1, 0.0, 0.3])})).save(path)
    pipe = DopeSlam(Slide(), World({"Yogurt": np.array([1.1, 0.8, 0.3])}), T_BASE_CAM, DIMS, retire=None)
    pipe.store = ObjectStore.load(path, dims=DIMS)
    w = pipe.detector
    for k in range(51):
        t = 0.1 * k
        pipe.on_image(CameraFrame(t, INFO, None, w.depth(t)))
        pipe.on_scan(LidarScan(t + 0.05, np.zeros((0, 3)), np.zeros(0)))
    store = pipe.finish().store
    assert len(store.labels()) == 2  # the stale one and the new one
