"""The depth path of DOPESLAM (paper section 3.5): depth maps turned into images DOPE can read.

RGB is useless in the dark; the D435i's depth (active IR projector) is not. The depth map is sliced
to a detection window [near, far]: depths inside map linearly to intensities, pixels nearer than the
window (and invalid zeros) become one uniform value, pixels farther another, so the object inside the
window stands out against flat surroundings. Five 3x3 median filters then remove the stereo speckle
and holes, and one sharpening filter restores the edges the medians soften.

Beyond the paper: :func:`sliding_windows` steps the window through the available range, so objects
beyond a single window's reach (~110 cm in the paper) are found too.
"""
from __future__ import annotations

import cv2
import numpy as np

NEAR_VALUE = 0.0  # intensity of pixels nearer than the window (and of invalid depth)
FAR_VALUE = 1.0  # intensity of pixels beyond the window
SHARPEN = np.array([[0, -1, 0], [-1, 5, -1], [0, -1, 0]], dtype=np.float32)


def slice_depth(depth_m: np.ndarray, near: float, far: float,
                near_value: float = NEAR_VALUE, far_value: float = FAR_VALUE) -> np.ndarray:
    """Map depths in [near, far] linearly to [0.1, 0.9]; below near (or 0 = no return) -> near_value,
    beyond far -> far_value. Returns float32 in [0, 1]."""
    if not far > near:
        raise ValueError(f"depth window: far ({far}) must exceed near ({near})")
    z = np.asarray(depth_m, dtype=np.float32)
    out = 0.1 + 0.8 * (z - near) / (far - near)
    out = np.where(z > far, far_value, out)
    out = np.where((z < near) | ~(z > 0), near_value, out)
    return out.astype(np.float32)


def clean(img: np.ndarray, medians: int = 5, sharpen: bool = True) -> np.ndarray:
    """``medians`` passes of a 3x3 median filter, then one 3x3 sharpening filter (clipped to [0, 1])."""
    x = np.asarray(img, dtype=np.float32)
    for _ in range(medians):
        x = cv2.medianBlur(x, 3)
    if sharpen:
        x = cv2.filter2D(x, -1, SHARPEN, borderType=cv2.BORDER_REPLICATE)
    return np.clip(x, 0.0, 1.0)


def preprocess_depth(depth_m: np.ndarray, near: float, far: float, medians: int = 5, sharpen: bool = True) -> np.ndarray:
    """Slice to the window, then clean: the single-channel image (float32 in [0, 1]) fed to DOPE."""
    return clean(slice_depth(depth_m, near, far), medians, sharpen)


def sliding_windows(range_min: float = 0.3, range_max: float = 2.0, size: float = 0.3,
                    overlap: float = 0.1) -> list[tuple[float, float]]:
    """Windows of ``size`` m stepping by ``size - overlap`` so that an object (shorter than the
    overlap) always lies wholly inside at least one window, covering [range_min, range_max]."""
    if not size > overlap >= 0:
        raise ValueError(f"sliding windows: need size ({size}) > overlap ({overlap}) >= 0")
    if not range_max > range_min:
        raise ValueError(f"sliding windows: range_max ({range_max}) must exceed range_min ({range_min})")
    out = []
    near = range_min
    while True:
        out.append((round(near, 6), round(near + size, 6)))
        if near + size >= range_max:
            break
        near += size - overlap
    return out


# --- which windows hold anything: the floor is fitted and left out -----------------------------------

def depth_points(depth_m: np.ndarray, K: np.ndarray, step: int = 2) -> np.ndarray:
    """(N, 3) camera-frame points of every ``step``-th pixel (rows and columns) with a valid depth."""
    z = np.asarray(depth_m, dtype=np.float32)[::step, ::step]
    vv, uu = np.mgrid[0:z.shape[0], 0:z.shape[1]]
    ok = np.isfinite(z) & (z > 0)
    u, v, d = uu[ok].astype(np.float64) * step, vv[ok].astype(np.float64) * step, z[ok].astype(np.float64)
    x = (u - K[0, 2]) / K[0, 0] * d
    y = (v - K[1, 2]) / K[1, 1] * d
    return np.stack([x, y, d], axis=1)


def fit_floor(points: np.ndarray, iterations: int = 80, tolerance_m: float = 0.015, max_tilt_deg: float = 30.0,
              min_support: float = 0.2, height_range=(0.05, 2.5), seed: int = 0) -> tuple[np.ndarray, float] | None:
    """The floor as ``(n, d)`` with ``n . X + d`` = height above it (n points up, towards the camera),
    fitted by RANSAC to the camera-frame points below the optical axis (y > 0 in the optical frame).

    A plane counts only when its normal is within ``max_tilt_deg`` of the camera's up (-y), it holds
    at least ``min_support`` of those points, and the camera is ``height_range`` above it; else None
    (no floor in view: callers then keep every window). Deterministic (fixed ``seed``)."""
    low = points[points[:, 1] > 0.02]
    if len(low) < 100:
        return None
    rng = np.random.default_rng(seed)
    if len(low) > 4000:
        low = low[rng.choice(len(low), 4000, replace=False)]
    cos_tilt = np.cos(np.radians(max_tilt_deg))
    best, best_n = None, 0
    for _ in range(iterations):
        a, b, c = low[rng.choice(len(low), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        if n[1] > 0:
            n = -n  # point up: the optical frame's y is down
        if -n[1] < cos_tilt:
            continue
        d = -float(n @ a)
        inl = int((np.abs(low @ n + d) < tolerance_m).sum())
        if inl > best_n:
            best, best_n = (n, d), inl
    if best is None or best_n < min_support * len(low):
        return None
    n, d = best
    inl = low[np.abs(low @ n + d) < tolerance_m]  # least-squares refit on the inliers
    centre = inl.mean(axis=0)
    _, _, vt = np.linalg.svd(inl - centre, full_matrices=False)
    n = vt[2] if vt[2][1] < 0 else -vt[2]
    d = -float(n @ centre)
    if not height_range[0] <= d <= height_range[1]:
        return None
    return n, d


def window_content(depth_m: np.ndarray, K: np.ndarray, windows, floor=None, step: int = 2,
                   min_height_m: float = 0.04, noise_sigmas: float = 4.0, sigma_at_1m: float = 0.0042) -> list[int]:
    """Per window, the number of sampled pixels (every ``step``-th) inside it that stand above the floor
    by more than ``max(min_height_m, noise_sigmas * sigma(z))`` (sigma(z) = ``sigma_at_1m`` z^2, the
    D435i's published RMS error). ``floor``: ``(n, d)`` from :func:`fit_floor`, or None to fit it here;
    with no floor found every window counts as full (a large number)."""
    pts = depth_points(depth_m, K, step)
    if floor is None:
        floor = fit_floor(pts)
    if floor is None:
        return [np.iinfo(np.int32).max] * len(windows)
    n, d = floor
    z = pts[:, 2]
    above = (pts @ n + d) > np.maximum(min_height_m, noise_sigmas * sigma_at_1m * z * z)
    za = z[above]
    return [int(((za >= near) & (za <= far)).sum()) for near, far in windows]
