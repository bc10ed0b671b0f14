"""Shape check for depth detections: does the detected class's cuboid explain the object the depth image shows?

In darkness the colour check (:mod:`stack.dope.colour_names`) has nothing to go on, and the depth
network's typical mistake is a wrong class on a right object: the place is right, the class is not.
The only class cue depth keeps is shape: the classes' cuboids differ in width and depth by a few
centimetres, which the D435i resolves at the 1-2 m it sees objects from when many pixels are averaged.

What is measured, for one detection at its depth-fitted pose:

1. The object's pixels: the depth pixels at about the detection's range (a band around the median
   depth inside its silhouette), connected to the silhouette's centre, row by row from the object's
   top edge down (runs that overlap the row above). A stand or support below joins them, often as
   wide as the object, so only the rows 1.5-6 cm under the top edge are used (``rows_m``): the
   object itself for every class at least 6 cm tall, below its top face.
2. From those rows: the object's left and right image edges, and per image column the median depth
   of its front surface. With the camera's rows about level, a vertical face has one depth per
   column, so the columns trace the object's outline seen from above (one or two visible faces).
3. For a footprint of ``a`` by ``b`` metres: at every yaw (a 3 degree grid, then a finer one around
   the best), the one placement whose outermost corners touch the observed left and right edges (two
   linear equations; each edge also a third of a pixel either way, as a pixel edge is known to a
   pixel), and the RMS depth residual of its front faces against the observed outline (a ray cast per
   column). The smallest over the placements says how well a box of that size, standing there,
   explains the depth.
4. The detected class's footprint is its two horizontal sizes (the axis of its fitted pose closest
   to the image's vertical is its height); any other class may stand on any of its three faces.

A footprint too big for the object has to turn its long face away to fit between the edges, and
then its faces slant where the object's do not; one too small has to stand further back to span
them. :func:`shape_costs` returns the residual (metres) per class, :func:`shape_verdict` the check:
the detected class fails when its own residual exceeds ``min_residual_m`` and is ``ratio`` times the
best other class's. A detection whose object is cut by the image border, touched by a nearer surface
at its edges, or seen through too few pixels gets no verdict (it passes).

Pure numpy and OpenCV (no simulator imports).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from stack.dope.depth_refine import BOX_CORNER_SIGNS

THETAS = np.radians(np.arange(0.0, 180.0, 3.0))  # yaw grid: a rectangle repeats every half turn
CLIP_M = 0.03  # a column's residual counts at most this much (a miss, a stray pixel)


@dataclass
class ShapeObservation:
    """The object under a detection, as the depth image shows it (pixel coordinates of the full image)."""

    z_front: float  # median depth inside the detection's silhouette (m)
    top_v: int  # the object's top row
    rows: tuple[int, int]  # the band of rows the outline is taken from (first, last)
    left_u: float  # the object's left and right edges (pixel boundaries)
    right_u: float
    cols: np.ndarray  # columns with an outline depth
    z_cols: np.ndarray  # median front-surface depth per column (m)
    noise_m: float  # the columns' depth noise (RMS standard error of their medians, from their rows' spread)


def _corners_px(T_cam_obj: np.ndarray, dims, K: np.ndarray) -> np.ndarray | None:
    half = np.asarray(dims, dtype=float) / 2.0
    P = (BOX_CORNER_SIGNS * half) @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    if np.any(P[:, 2] <= 0.05):
        return None
    return np.column_stack([K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2], K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]])


_SQUARE_3x3 = np.ones((3, 3), np.uint8)


def closing_3x3(mask: np.ndarray) -> np.ndarray:
    """A boolean mask's closing by a 3x3 square, nothing beyond the edges: the pixels of
    ``scipy.ndimage.binary_closing(mask, np.ones((3, 3)))`` (its dilation, then its erosion, with a
    border of zeros), by OpenCV's morphology on bytes, about fifty times faster."""
    u = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    grown = cv2.dilate(u, _SQUARE_3x3, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return cv2.erode(grown, _SQUARE_3x3, borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)


def column_medians(x: np.ndarray) -> np.ndarray:
    """Each column's median of its numbers, NaN left out: ``np.nanmedian(x, axis=0)`` for a 2D float
    array of fewer than 600 rows with a number in every column, the same values in its dtype (NumPy's
    path for such arrays: the two middle numbers of the sorted column, ``(low + high) / 2``), without
    its masked-array machinery."""
    s = np.sort(x, axis=0)  # NaN sorts last
    n = np.count_nonzero(~np.isnan(x), axis=0)
    high = n // 2
    low = np.where(n % 2 == 1, high, high - 1)
    cols = np.arange(x.shape[1])
    mid = s[low, cols] + s[high, cols]
    return np.true_divide(mid, 2.0, out=mid)


def _runs(row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cols = np.flatnonzero(row)
    if cols.size == 0:
        return cols, cols
    cut = np.flatnonzero(np.diff(cols) > 1)
    return np.concatenate((cols[:1], cols[cut + 1])), np.concatenate((cols[cut], cols[-1:]))


def _track(mask: np.ndarray, v: int, left: int, right: int, step: int,
           stop: int | None = None) -> list[tuple[int, int, int]]:
    """Rows from ``v`` (exclusive) in direction ``step`` (up to row ``stop``): the union of the runs
    overlapping the row before."""
    out = []
    v += step
    end = mask.shape[0] if stop is None else min(mask.shape[0], stop + 1)
    while 0 <= v < end:
        s, e = _runs(mask[v])
        ov = (s <= right + 1) & (e >= left - 1)
        if not ov.any():
            break
        left, right = int(s[ov].min()), int(e[ov].max())
        out.append((v, left, right))
        v += step
    return out


def observe(depth_m: np.ndarray, K, T_cam_obj: np.ndarray, dims, band_m: tuple[float, float] = (0.06, 0.20),
            context_m: float = 0.35, rows_m: tuple[float, float] = (0.015, 0.06), min_rows: int = 4,
            min_cols: int = 6) -> ShapeObservation | None:
    """The object under a detection (see the module's steps 1-2); None where the depth cannot say."""
    depth = np.asarray(depth_m, dtype=np.float32)
    K = np.asarray(K, dtype=float)
    H, W = depth.shape
    uv = _corners_px(np.asarray(T_cam_obj, dtype=float), dims, K)
    if uv is None:
        return None
    (u0, v0), (u1, v1) = uv.min(axis=0), uv.max(axis=0)
    cu, cv = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
    if not (0 <= cu < W and 0 <= cv < H):
        return None
    hu, hv = max(1.0, 0.25 * (u1 - u0)), max(1.0, 0.25 * (v1 - v0))
    inner = depth[int(max(0, cv - hv)):int(min(H, cv + hv + 1)), int(max(0, cu - hu)):int(min(W, cu + hu + 1))]
    vals = inner[inner > 0]
    if vals.size < 10:
        return None
    zf = float(np.median(vals))
    fx, fy = K[0, 0], K[1, 1]
    r = int(context_m * fx / zf)
    ra, rb, rl, rr = max(0, int(cv) - r), min(H, int(cv) + r + 1), max(0, int(cu) - r), min(W, int(cu) + r + 1)
    roi = depth[ra:rb, rl:rr]
    fg = (roi > zf - band_m[0]) & (roi < zf + band_m[1])
    fg |= closing_3x3(fg)  # fill single dropouts
    sv, su = min(int(round(cv)) - ra, fg.shape[0] - 1), min(int(round(cu)) - rl, fg.shape[1] - 1)
    s, e = _runs(fg[sv])
    if s.size == 0:
        return None
    gap = np.where((s <= su) & (e >= su), 0, np.minimum(np.abs(s - su), np.abs(e - su)))
    k = int(np.argmin(gap))
    if gap[k] > hu:
        return None
    up = _track(fg, sv, int(s[k]), int(e[k]), -1)[::-1]
    prof = np.array(up + [(sv, int(s[k]), int(e[k]))], dtype=int)
    top = int(prof[0, 0])
    if top == 0:  # cut by the region (or the image) above
        return None
    first = top + max(3, int(math.ceil(rows_m[0] * fy / zf)))
    last = top + int(rows_m[1] * fy / zf)
    down = _track(fg, sv, int(s[k]), int(e[k]), +1, stop=last)
    prof = np.array(up + [(sv, int(s[k]), int(e[k]))] + down, dtype=int)
    band = prof[(prof[:, 0] >= first) & (prof[:, 0] <= last)]
    if len(band) < min_rows:
        return None
    left, right = int(np.percentile(band[:, 1], 10)), int(np.ceil(np.percentile(band[:, 2], 90)))
    if left <= 0 or right >= fg.shape[1] - 1:
        return None  # reaches the region's (or the image's) side
    # a nearer surface just beside or above the object hides part of it: no verdict
    near = zf - band_m[0]
    rows = slice(band[0, 0], band[-1, 0] + 1)
    beside = (roi[rows, max(0, left - 3):left], roi[rows, right + 1:right + 4], roi[max(0, top - 3):top, left:right + 1])
    for side in beside:
        seen = side[side > 0]
        if seen.size and np.mean(seen < near) > 0.3:
            return None
    # per column: the median depth of the object's pixels in the band
    sub = roi[rows]
    m = fg[rows].copy()
    span = np.zeros_like(m)
    for i, (_, a, b) in enumerate(band):
        span[i, a:b + 1] = True
    m &= span & (sub > 0)
    cols = np.arange(left, right + 1)
    cnt = m[:, cols].sum(axis=0)
    zs = np.where(m[:, cols], sub[:, cols], np.nan)
    ok = cnt >= max(3, len(band) // 3)
    if ok.sum() < min_cols:
        return None
    with np.errstate(all="ignore"):
        z_cols = column_medians(zs[:, ok])
        mad = column_medians(np.abs(zs[:, ok] - z_cols))
    # a median of n samples: 1.25 sigma / sqrt(n); sigma from the median absolute deviation
    noise = float(np.sqrt(np.mean((1.25 * 1.4826 * mad) ** 2 / cnt[ok])))
    return ShapeObservation(zf, top + ra, (int(band[0, 0]) + ra, int(band[-1, 0]) + ra),
                            left + rl - 0.5, right + rl + 0.5, cols[ok] + rl, z_cols.astype(float), noise)


def _placement_rms(obs: ShapeObservation, su: np.ndarray, a: np.ndarray, b: np.ndarray, th: np.ndarray,
                   sl: np.ndarray, sr: np.ndarray, clip_m: float) -> np.ndarray:
    """RMS depth residual of footprints ``a`` x ``b`` at yaw ``th`` placed between the edge rays of slopes
    ``sl``, ``sr`` (all arrays of one length n); ``su``: the observed columns' ray slopes."""
    a, b = a[:, None], b[:, None]
    e1 = np.stack([np.cos(th), np.sin(th)], axis=1)  # (n, 2): the footprint's axes in (X, Z)
    e2 = np.stack([-np.sin(th), np.cos(th)], axis=1)
    sg = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=float)
    q = ((sg[None, :, 0, None] * a[:, :, None] / 2) * e1[:, None, :]  # (n, 4, 2) corners about the centre
         + (sg[None, :, 1, None] * b[:, :, None] / 2) * e2[:, None, :])
    zc = float(np.median(obs.z_cols)) + 0.5 * np.minimum(a[:, 0], b[:, 0])
    C = np.stack([0.5 * (sl + sr) * zc, zc], axis=1)
    rows = np.arange(len(th))
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(3):  # the outermost corners depend on where the box stands; settles in one or two passes
            P = C[:, None, :] + q
            ratio = P[..., 0] / np.maximum(P[..., 1], 1e-6)
            qi, qj = q[rows, ratio.argmin(axis=1)], q[rows, ratio.argmax(axis=1)]
            # the leftmost corner on the left edge's ray, the rightmost on the right's: X - s Z = 0
            r1, r2 = sl * qi[:, 1] - qi[:, 0], sr * qj[:, 1] - qj[:, 0]
            Cz = (r1 - r2) / (sr - sl)
            C = np.stack([r1 + sl * Cz, Cz], axis=1)
        # depth along each column's ray (X = s Z) to the first face it meets, in the footprint's axes
        o1, o2 = -(C * e1).sum(axis=1)[:, None], -(C * e2).sum(axis=1)[:, None]
        # the (n, N) arrays below are each written in place once made: the same arithmetic, fewer of them
        d1 = su[None, :] * e1[:, 0, None]
        d1 += e1[:, 1, None]
        d2 = su[None, :] * e2[:, 0, None]
        d2 += e2[:, 1, None]
        t1a, t1b = (-a / 2 - o1) / d1, np.divide(a / 2 - o1, d1, out=d1)
        t2a, t2b = (-b / 2 - o2) / d2, np.divide(b / 2 - o2, d2, out=d2)
        tmin = np.minimum(t1a, t1b)
        tmax = np.maximum(t1a, t1b, out=t1b)
        np.maximum(tmin, np.minimum(t2a, t2b), out=tmin)  # the later of the two slabs' entries
        np.minimum(tmax, np.maximum(t2a, t2b, out=t2b), out=tmax)  # the earlier of their exits
        hit = tmax >= tmin
        hit &= tmin > 0
        # the depth residual where a face is hit, clip_m where none is; clipped to +-clip_m
        res = np.subtract(obs.z_cols[None, :], tmin, out=tmin)
    res[~hit] = clip_m
    np.clip(res, -clip_m, clip_m, out=res)
    rms = np.sqrt(np.mean(np.multiply(res, res, out=res), axis=1))
    rms[~(C[:, 1] > 0.05) | ~np.isfinite(rms)] = math.inf
    return rms


def footprint_residuals(obs: ShapeObservation, K, sizes, thetas: np.ndarray = THETAS, edge_px: float = 0.35,
                        clip_m: float = CLIP_M) -> np.ndarray:
    """RMS depth residual (m) of the best-placed footprint of each ``(a, b)`` in ``sizes`` (module step 3).

    The yaw on the grid ``thetas``, then within one grid step of the best at a tenth of it. An edge is
    known to a pixel: the object's width is also tried ``edge_px`` pixels wider and narrower each side."""
    K = np.asarray(K, dtype=float)
    ab = np.asarray(sizes, dtype=float).reshape(-1, 2)
    fx, cx = K[0, 0], K[0, 2]
    su = (obs.cols - cx) / fx
    widen = np.array([-edge_px, 0.0, edge_px])
    sL, sR = (obs.left_u - widen - cx) / fx, (obs.right_u + widen - cx) / fx  # (3,) edge ray slopes
    nS, nE = len(ab), len(widen)

    def best(th: np.ndarray) -> np.ndarray:  # th: (nS, nT) yaws per size -> (nS, nT) over the edges' best
        nT = th.shape[1]
        rms = _placement_rms(obs, su, np.repeat(ab[:, 0], nT * nE), np.repeat(ab[:, 1], nT * nE),
                             np.repeat(th.ravel(), nE), np.tile(sL, nS * nT), np.tile(sR, nS * nT), clip_m)
        return rms.reshape(nS, nT, nE).min(axis=2)

    coarse = best(np.tile(thetas, (nS, 1)))
    step = float(thetas[1] - thetas[0]) if len(thetas) > 1 else 0.0
    th0 = thetas[np.argmin(coarse, axis=1)]
    fine = best(th0[:, None] + np.linspace(-step, step, 11)[None, :])
    return np.minimum(coarse.min(axis=1), fine.min(axis=1))


def up_axis(T_cam_obj: np.ndarray) -> int:
    """The object axis closest to the image's vertical (the camera's y axis): the detected class's height."""
    return int(np.argmax(np.abs(np.asarray(T_cam_obj)[1, :3])))


def shape_costs(obs: ShapeObservation, K, dims: dict, cls: str, T_cam_obj: np.ndarray, **kw) -> dict[str, float]:
    """Residual (m) per class: the detected class standing as detected; any other class on any face."""
    k = up_axis(T_cam_obj)
    owner, sizes = [], []
    for c, d in dims.items():
        d = np.asarray(d, dtype=float)
        for up in ([k] if c == cls else [0, 1, 2]):
            owner.append(c)
            sizes.append([d[i] for i in range(3) if i != up])
    rms = footprint_residuals(obs, K, sizes, **kw)
    out: dict[str, float] = {}
    for c, r in zip(owner, rms):
        out[c] = min(out.get(c, math.inf), float(r))
    return out


@dataclass
class ShapeVerdict:
    ok: bool  # False: another class explains the depth clearly better than the detected one
    own_m: float  # the detected class's residual
    best_other: str  # the class with the smallest residual among the others
    best_other_m: float
    noise_m: float  # the outline's own depth noise (:attr:`ShapeObservation.noise_m`)

    def as_dict(self) -> dict:
        return {"pass": self.ok, "residual_m": self.own_m, "best_other": self.best_other,
                "best_other_residual_m": self.best_other_m, "noise_m": self.noise_m}


def shape_verdict(depth_m: np.ndarray, K, T_cam_obj: np.ndarray, dims: dict, cls: str,
                  min_residual_m: float = 0.006, ratio: float = 1.5) -> ShapeVerdict | None:
    """The shape check of one detection (module docstring); None where the depth gives no verdict."""
    obs = observe(depth_m, K, T_cam_obj, dims[cls])
    if obs is None or len(dims) < 2:
        return None
    costs = shape_costs(obs, K, dims, cls, T_cam_obj)
    own = costs[cls]
    other = min((c for c in costs if c != cls), key=costs.get)
    ok = not (own > min_residual_m and own > ratio * costs[other])
    return ShapeVerdict(bool(ok), own, other, costs[other], obs.noise_m)
