"""``render_mode="rgb_array"`` for the labelling envs: the camera image with the frame's detections
drawn on it, beside a top-down map of the LiDAR map, the estimated path, the true objects and the
current labels. Drawn with OpenCV (a few milliseconds a frame)."""
from __future__ import annotations

import cv2
import numpy as np

from testbed.scoring import FALSE_LABEL_M

PANEL_H = 240
CAM_W = 320
MAP_W = 320
# one colour per class (RGB), in the catalog's class order
CLASS_COLORS = [(245, 140, 20), (200, 30, 90), (230, 200, 30), (190, 30, 40), (70, 120, 200), (40, 170, 200),
                (120, 200, 80), (160, 90, 200)]
EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]


def _color(c: int) -> tuple:
    return CLASS_COLORS[int(c) % len(CLASS_COLORS)]


class TopDownMap:
    """The static part of the map panel, drawn once per episode; ``draw`` adds the moving parts."""

    def __init__(self, map_xy: np.ndarray, traj_xy: np.ndarray, truth_xy: np.ndarray, size=(MAP_W, PANEL_H)):
        self.w, self.h = size
        pts = [a.reshape(-1, 2) for a in (traj_xy, truth_xy) if len(a)]
        if len(map_xy):
            lo_m, hi_m = np.percentile(map_xy, 1, axis=0), np.percentile(map_xy, 99, axis=0)
            pts.append(np.array([lo_m, hi_m]))
        allp = np.vstack(pts) if pts else np.zeros((1, 2))
        lo, hi = allp.min(axis=0) - 0.5, allp.max(axis=0) + 0.5
        self.scale = min((self.w - 10) / max(hi[0] - lo[0], 1e-3), (self.h - 10) / max(hi[1] - lo[1], 1e-3))
        self.centre = (lo + hi) / 2
        self.base = np.full((self.h, self.w, 3), 250, dtype=np.uint8)
        if len(map_xy):
            uv = self.px(map_xy)
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < self.w) & (uv[:, 1] >= 0) & (uv[:, 1] < self.h)
            self.base[uv[ok, 1], uv[ok, 0]] = (150, 150, 150)
        self.truth_uv = self.px(truth_xy) if len(truth_xy) else np.zeros((0, 2), int)

    def px(self, xy: np.ndarray) -> np.ndarray:
        """Map x, y (m) -> pixel column, row (x to the right, y up)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        u = (xy[:, 0] - self.centre[0]) * self.scale + self.w / 2
        v = self.h / 2 - (xy[:, 1] - self.centre[1]) * self.scale
        return np.column_stack([u, v]).round().astype(int)

    def draw(self, path_xy: np.ndarray, robot_T: np.ndarray, truth_cls, labels: list, dets: list) -> np.ndarray:
        img = self.base.copy()
        if len(path_xy) > 1:
            cv2.polylines(img, [self.px(path_xy).reshape(-1, 1, 2)], False, (60, 90, 220), 1, cv2.LINE_AA)
        for (u, v), c in zip(self.truth_uv, truth_cls):
            cv2.circle(img, (int(u), int(v)), 5, (0, 0, 0), 1, cv2.LINE_AA)
            cv2.circle(img, (int(u), int(v)), 2, _color(c), -1)
        for xy, c in dets:
            u, v = self.px(xy[:2])[0]
            cv2.circle(img, (int(u), int(v)), 2, _color(c), -1)
        for xy, c, err in labels:
            u, v = self.px(xy[:2])[0]
            col = (220, 0, 0) if err is not None and err > FALSE_LABEL_M else _color(c)
            cv2.drawMarker(img, (int(u), int(v)), col, cv2.MARKER_TILTED_CROSS, 9, 2)
        if robot_T is not None:
            p = robot_T[:2, 3]
            h = p + 0.4 * robot_T[:2, 0]
            (u0, v0), (u1, v1) = self.px(np.array([p, h]))
            cv2.arrowedLine(img, (int(u0), int(v0)), (int(u1), int(v1)), (20, 20, 20), 2, cv2.LINE_AA, tipLength=0.4)
        cv2.putText(img, "map (top-down)", (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (60, 60, 60), 1, cv2.LINE_AA)
        return img


def camera_panel(image: np.ndarray | None, full_size: tuple, kps: list, size=(CAM_W, PANEL_H),
                 caption: str = "") -> np.ndarray:
    """The camera image (any size) scaled to the panel, with each detection's cuboid drawn from its
    key points (given in full-resolution pixels); green edges passed FPR, red failed."""
    w, h = size
    if image is None:
        panel = np.zeros((h, w, 3), dtype=np.uint8)
    else:
        panel = np.ascontiguousarray(cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR))
    sx, sy = w / full_size[0], h / full_size[1]
    for kp, c, fpr in kps:
        uv = np.asarray(kp, dtype=float).reshape(9, 2) * (sx, sy)
        edge_col = (40, 220, 40) if fpr else (230, 30, 30)
        for a, b in EDGES:
            if np.all(np.isfinite(uv[[a, b]])):
                cv2.line(panel, tuple(uv[a].round().astype(int)), tuple(uv[b].round().astype(int)), edge_col, 1,
                         cv2.LINE_AA)
        if np.all(np.isfinite(uv[8])):
            cv2.circle(panel, tuple(uv[8].round().astype(int)), 3, _color(c), -1)
    if caption:
        cv2.putText(panel, caption, (4, h - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
    return panel


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    sep = np.full((left.shape[0], 2, 3), 255, dtype=np.uint8)
    return np.ascontiguousarray(np.concatenate([left, sep, right], axis=1))
