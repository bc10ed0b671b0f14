"""A loop-closer double for the pipeline's unit tests (``stack.interfaces.LoopCloser``)."""
from __future__ import annotations

import numpy as np


class RecordingLoopCloser:
    """Sees what the pipeline hands a loop closer; 'corrects' the trajectory by ``SHIFT`` (1 m along y)
    and, at the end, fuses every detection again with the corrected poses."""

    SHIFT = np.array([[1.0, 0, 0, 0], [0, 1, 0, 1.0], [0, 0, 1, 0], [0, 0, 0, 1]])

    def __init__(self, shift: np.ndarray | None = None):
        if shift is not None:
            self.SHIFT = np.asarray(shift, dtype=float)
        self.scans, self.images, self.fused = [], [], []

    def on_scan(self, odometry, T_map_base):
        self.scans.append(None if T_map_base is None else float(T_map_base[0, 3]))

    def on_image(self, frame):
        self.images.append(frame.stamp)

    def on_fused(self, detection):
        self.fused.append(detection)

    def finish(self, stamps, T_map_base):
        return self.SHIFT @ T_map_base

    def refuse(self, store, pose_at, T_base_cam):
        from stack.fusion import fuse

        for det in self.fused:
            store.add(fuse(det, lambda t: self.SHIFT @ pose_at(t), T_base_cam))
        return store

    def map_points(self):
        return [np.zeros((1, 3))]
