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
