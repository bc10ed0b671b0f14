"""Depth refinement of a DOPE pose: slide the object along its viewing ray until its cuboid's front
surface meets the aligned depth image.

PnP on a few key points fixes where an object is in the image far better than how far away it is
(the range comes from the object's apparent size; a corner off by a pixel or two moves it by
centimetres). An RGB-D camera measures the range directly. This module ray-casts the detected
cuboid into the camera, compares its expected depth with the measured depth inside the object's
silhouette, and scales the translation along the ray by the robust (median) residual, in a few
passes with a shrinking gate so background and occluders drop out. The image position of the
object, and its orientation, are kept.

Pure numpy (no simulator imports): runs on a robot's RGB-D frames as on simulated ones.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class DepthFit:
    """Result of :func:`refine_translation`."""

    T_cam_obj: np.ndarray  # refined pose (4x4); the input pose when not ``ok``
    ok: bool  # enough consistent depth pixels to trust the refinement
    shift_m: float  # range change along the viewing ray (positive = further away)
    n_pixels: int  # silhouette pixels with a valid measured depth
    inlier_frac: float  # fraction of those within the final gate


def _ray_box_depth(T_cam_obj: np.ndarray, dims, K: np.ndarray, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """Optical-axis depth (z) of the first hit of the rays through pixels (us, vs) on the cuboid; NaN = miss."""
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    d_cam = np.empty((len(us), 3))  # z = 1 per unit
    np.divide(us - cx, fx, out=d_cam[:, 0])
    np.divide(vs - cy, fy, out=d_cam[:, 1])
    d_cam[:, 2] = 1.0
    o = -R.T @ t  # camera centre in the object frame
    d = d_cam @ R  # directions in the object frame (R^T d for each row)
    half = np.asarray(dims, dtype=float) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - o) * inv
        t2 = (half - o) * inv
    # the slabs' entry and exit, NaN (a ray in a face's plane) left out: what nanmax/nanmin compute,
    # without their checks (a ray's direction is never zero in all three axes)
    tmin = np.fmax.reduce(np.minimum(t1, t2), axis=1)
    tmax = np.fmin.reduce(np.maximum(t1, t2), axis=1)
    hit = (tmax >= tmin) & (tmax > 0)
    return np.where(hit, np.maximum(tmin, 0.0), np.nan)  # parameter along d_cam, whose z is 1 -> depth


BOX_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
"""(8, 3): a box's corners about its centre in units of its half sizes (any order: silhouettes and extents)."""


def silhouette_pixels(T_cam_obj: np.ndarray, dims, K: np.ndarray, shape: tuple[int, int],
                      shrink: float = 0.7, step: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(us, vs, z_expected) of pixels (every ``step``-th) whose rays hit the cuboid shrunk by ``shrink``
    about its centre (so silhouette edges, where depth is mixed, are left out)."""
    h, w = shape
    half = np.asarray(dims, dtype=float) / 2.0
    pts = (BOX_CORNER_SIGNS * half) @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    if np.any(pts[:, 2] <= 0.05):
        return np.empty(0), np.empty(0), np.empty(0)
    uv = (pts[:, :2] / pts[:, 2:3]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    u0, v0 = np.clip(np.floor(uv.min(axis=0)).astype(int), 0, [w - 1, h - 1])
    u1, v1 = np.clip(np.ceil(uv.max(axis=0)).astype(int), 0, [w - 1, h - 1])
    if u1 <= u0 or v1 <= v0:
        return np.empty(0), np.empty(0), np.empty(0)
    cols = np.arange(u0, u1 + 1, step, dtype=float)
    rows = np.arange(v0, v1 + 1, step, dtype=float)
    us, vs = np.tile(cols, len(rows)), np.repeat(rows, len(cols))  # row-major, as np.mgrid's
    z = _ray_box_depth(T_cam_obj, np.asarray(dims, dtype=float) * shrink, K, us, vs)
    keep = np.isfinite(z)
    # the expected depth is that of the full-size box along the same rays
    z_full = _ray_box_depth(T_cam_obj, dims, K, us[keep], vs[keep])
    return us[keep], vs[keep], z_full


def refine_translation(T_cam_obj: np.ndarray, dims, K: np.ndarray, depth_m: np.ndarray,
                       gates=(0.4, 0.15, 0.05), min_pixels: int = 20, min_inlier_frac: float = 0.3,
                       max_shift_frac: float = 0.5) -> DepthFit:
    """Scale the translation of ``T_cam_obj`` along its ray so the cuboid's depth matches ``depth_m``.

    ``depth_m``: (H, W) metres aligned to the image of ``K``, 0 or NaN = no return. Each pass takes
    the median of (measured - expected) depth over silhouette pixels whose residual is within the
    pass's gate (metres) and moves the object by it. ``ok`` is False (and the pose unchanged) with
    fewer than ``min_pixels`` valid pixels, fewer than ``min_inlier_frac`` of them within the last
    gate, or a total shift beyond ``max_shift_frac`` of the range.
    """
    T0 = np.asarray(T_cam_obj, dtype=float)
    depth = np.asarray(depth_m)  # read where the silhouette falls, then as float64 (not the whole image)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be a 2D image, got shape {depth.shape}")
    K = np.asarray(K, dtype=float)
    z0 = T0[2, 3]
    if z0 <= 0:
        return DepthFit(T0, False, 0.0, 0, 0.0)
    T = T0.copy()
    n_valid, frac = 0, 0.0
    for gate in gates:
        us, vs, z_exp = silhouette_pixels(T, dims, K, depth.shape)
        if len(us) == 0:
            return DepthFit(T0, False, 0.0, 0, 0.0)
        meas = depth[vs.astype(int), us.astype(int)].astype(np.float64)
        valid = np.isfinite(meas) & (meas > 0)
        n_valid = int(valid.sum())
        if n_valid < min_pixels:
            return DepthFit(T0, False, 0.0, n_valid, 0.0)
        r = meas[valid] - z_exp[valid]
        inl = np.abs(r) <= gate
        frac = float(inl.mean())
        if inl.sum() < min_pixels // 2:
            return DepthFit(T0, False, 0.0, n_valid, frac)
        dz = float(np.median(r[inl]))
        T[:3, 3] *= (T[2, 3] + dz) / T[2, 3]  # along the ray through the object's origin
    shift = float(np.linalg.norm(T[:3, 3]) - np.linalg.norm(T0[:3, 3]))
    ok = bool(frac >= min_inlier_frac and abs(T[2, 3] - z0) <= max_shift_frac * z0)
    return DepthFit(T if ok else T0, ok, shift if ok else 0.0, n_valid, frac)
