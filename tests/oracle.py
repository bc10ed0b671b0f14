"""A ground-truth "detector" for testing the harness around DOPE (a test double: never shipped)."""
from __future__ import annotations

import numpy as np

from stack.messages import Detection


class OracleDetector:
    def __init__(self, episode, noise_m: float = 0.01, max_range: float = 1.5, seed: int = 0):
        self.ep = episode
        self.noise = noise_m
        self.max_range = max_range
        self.rng = np.random.default_rng(seed)

    def detect(self, frame):
        out = []
        for t in self.ep.image_truth(frame):
            if t["in_front"] and t["distance_m"] <= self.max_range and t["visible_fraction"] > 0.5:
                T = t["T_cam_obj"].copy()
                T[:3, 3] += self.rng.normal(0, self.noise, 3)
                out.append(Detection(t["cls"], frame.stamp, T, t["keypoints_px"], np.ones(9), 10.0))
        return out
