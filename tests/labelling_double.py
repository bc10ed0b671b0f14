"""A test double for DOPE in the labelling-env tests: the truth with range-dependent noise and
occasional gross outliers that FPR flags most of the time (a test double: never shipped)."""
from __future__ import annotations

import numpy as np

from stack.messages import Detection


class NoisyOracle:
    def __init__(self, episode, seed: int = 0, max_range: float = 3.0, noise_per_m: float = 0.03,
                 outlier_rate: float = 0.2):
        self.ep = episode
        self.rng = np.random.default_rng([seed, episode.seed])
        self.max_range, self.noise_per_m, self.outlier_rate = max_range, noise_per_m, outlier_rate

    def _one(self, frame, t, stages: int):
        T = t["T_cam_obj"].copy()
        d = t["distance_m"]
        if self.rng.random() < self.outlier_rate:
            T[:3, 3] += self.rng.normal(0.0, 0.4, 3)
            fpr, belief = bool(self.rng.random() < 0.25), 40.0 + self.rng.random() * 20
        else:
            T[:3, 3] += self.rng.normal(0.0, self.noise_per_m * d * 6.0 / (stages + 2), 3)
            fpr, belief = bool(self.rng.random() > 0.05), 5.0 + 10.0 * d + self.rng.random()
        return Detection(t["cls"], frame.stamp, T, t["keypoints_px"], np.ones(9), belief, stages, fpr)

    def _visible(self, frame):
        return [t for t in self.ep.image_truth(frame)
                if t["in_front"] and t["distance_m"] <= self.max_range and t["visible_fraction"] > 0.3]

    def detect(self, frame):
        return [self._one(frame, t, 6) for t in self._visible(frame)]

    def detect_stages(self, frame, stage_counts=None):
        vis = self._visible(frame)
        return {s: [self._one(frame, t, s) for t in vis] for s in (stage_counts or range(1, 7))}
