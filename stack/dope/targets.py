"""DOPE training targets: belief maps (a Gaussian at each projected key point) and affinity maps
(at each corner, the unit vector pointing to the object's centroid), on the network's output grid.

Coordinates: an input pixel ``u`` (pixel centres at integers) maps to output cell coordinate
``(u + 0.5) / stride - 0.5``; :func:`to_input_px` is the inverse. Key points are drawn whether or
not the corner is occluded (DOPE predicts the whole cuboid), as long as they fall on the grid.
"""
from __future__ import annotations

import numpy as np

from stack.dope.net import N_AFFINITY, N_BELIEF, STRIDE


def to_output_coords(uv_px: np.ndarray, stride: int = STRIDE) -> np.ndarray:
    return (np.asarray(uv_px, dtype=np.float64) + 0.5) / stride - 0.5


def to_input_px(uv_out: np.ndarray, stride: int = STRIDE) -> np.ndarray:
    return (np.asarray(uv_out, dtype=np.float64) + 0.5) * stride - 0.5


def make_targets(keypoints_px: np.ndarray, class_index: np.ndarray, n_classes: int, out_hw: tuple[int, int],
                 stride: int = STRIDE, sigma: float = 1.0, radius: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Belief (n_classes*9, h, w) and affinity (n_classes*16, h, w) float32 targets.

    keypoints_px: (N, 9, 2) projected key points of N objects in input pixels (NaN = absent);
    class_index: (N,) class of each object. ``sigma`` (Gaussian) and ``radius`` (affinity disc) are in
    output cells. Where objects overlap the belief is the maximum and the affinity of the nearer
    key point (the one with the larger belief) wins.
    """
    h, w = out_hw
    belief = np.zeros((n_classes * N_BELIEF, h, w), np.float32)
    affinity = np.zeros((n_classes * N_AFFINITY, h, w), np.float32)
    kps = np.asarray(keypoints_px, dtype=np.float64).reshape(-1, 9, 2)
    cls = np.asarray(class_index, dtype=int).reshape(-1)
    if len(kps) != len(cls):
        raise ValueError(f"keypoints_px has {len(kps)} objects but class_index {len(cls)}")
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    reach = int(np.ceil(max(3 * sigma, radius))) + 1
    for obj, c in zip(kps, cls):
        if not 0 <= c < n_classes:
            raise ValueError(f"class index {c} outside 0..{n_classes - 1}")
        pts = to_output_coords(obj, stride)
        centre = pts[8]
        for k in range(9):
            px, py = pts[k]
            if not (np.isfinite(px) and np.isfinite(py)):
                continue
            if px < -reach or py < -reach or px > w - 1 + reach or py > h - 1 + reach:
                continue
            x0, x1 = max(0, int(np.floor(px)) - reach), min(w, int(np.ceil(px)) + reach + 1)
            y0, y1 = max(0, int(np.floor(py)) - reach), min(h, int(np.ceil(py)) + reach + 1)
            if x0 >= x1 or y0 >= y1:
                continue
            d2 = (xs[y0:y1, x0:x1] - px) ** 2 + (ys[y0:y1, x0:x1] - py) ** 2
            g = np.exp(-d2 / (2 * sigma * sigma)).astype(np.float32)
            ch = c * N_BELIEF + k
            win = belief[ch, y0:y1, x0:x1]
            if k < 8 and np.all(np.isfinite(centre)):
                vec = centre - pts[k]
                norm = np.linalg.norm(vec)
                if norm > 1e-6:
                    vec = vec / norm
                    disc = (d2 <= radius * radius) & (g >= win)
                    a = c * N_AFFINITY + 2 * k
                    affinity[a, y0:y1, x0:x1][disc] = vec[0]
                    affinity[a + 1, y0:y1, x0:x1][disc] = vec[1]
            np.maximum(win, g, out=win)
    return belief, affinity
