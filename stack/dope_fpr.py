"""DOPE inference and the false-positive reduction (FPR) filter: camera frame in, object poses out.

Pipeline (paper sections 3.1 and 3.4):

1. The frame (RGB, or depth sliced to a window and cleaned, :mod:`stack.dope.depth_window`) is resized to
   the network's input size (320x240 by default) and run through :class:`stack.dope.net.DopeNet`,
   keeping the outputs of every stage, so one pass serves every stage count 1..6.
2. Per class, peaks of the smoothed belief maps (local maxima above ``peak_threshold``) give centroid
   and corner candidates; each corner joins the centroid its affinity vector points at (within
   ``angle_threshold``); peak positions are refined to sub-cell precision (belief-weighted centroid).
3. ``cv2.solvePnP`` (EPnP, then Levenberg-Marquardt) with the class's cuboid gives the pose in the
   camera optical frame. The shipped weights are trained with view-canonical labels (the face towards
   the camera is "front", :func:`stack.dope.train.canonical_order`), so the orientation is reported up to
   a half turn about the object's vertical axis; the position is not affected.
4. Depth refinement (RGB-D frames, on by default): PnP fixes where the object is in the image far
   better than its range, so the pose is slid along its viewing ray until the cuboid's front surface
   meets the aligned depth image (:mod:`stack.dope.depth_refine`). Orientation and image position are kept;
   the PnP-only pose stays in ``extra['pnp_pose']``.
5. FPR: the belief tensor of the class (its 9 maps of the evaluated stage, negative values clipped)
   is summed; a sharp, single prediction has a small sum, several objects or an unsure network a
   large one. A detection passes when its sum is at or below the threshold for (class, stage count).
   Thresholds are calibrated automatically (:func:`calibrate_threshold`: the largest recall whose
   precision stays at or above a target) and can be overridden by hand. Beyond the paper, on RGB-D
   frames a detection also fails FPR when the depth image does not support its cuboid (step 4's fit
   finds too few consistent pixels): a detection on a column or a wall rarely has the object's shape
   at the object's range.
6. Colour check (beyond the paper; the topological-map paper's colour-name verification, section 3.3 of
   ``001_...``): on lit RGB frames the colour-name histogram of the detected cuboid's silhouette is
   compared (cosine distance) with every class's colour model (``stack/weights/hog_colour.json``, fitted
   on our rendered data). A detection fails FPR when its own class's model is not the closest one
   (within ``colour_margin``) or is beyond that class's threshold. DOPE's typical false positive in the
   bundled scenes is a wrong class on a right object (an E on the Cookies box, a Mustard on the orange
   juice): depth supports such a cuboid, but its colours belong to the other class.
7. Shape check (beyond the paper; depth input): in darkness shape is the only class cue left. The
   object's outline seen from above (its front surface's depth per image column, between its image
   edges) is explained by every class's cuboid footprint in turn; a detection fails FPR when its own
   class's residual is above ``shape_min_residual_m`` and ``shape_ratio`` times another class's
   (:mod:`stack.dope.shape_check`). The depth network's typical error is such a wrong class on a right
   object.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.ndimage import maximum_filter

from stack.dope.colour_names import ColourModel, colour_names
from stack.dope.depth_refine import refine_translation
from stack.dope.depth_window import preprocess_depth, sliding_windows, window_content
from stack.dope.shape_check import shape_verdict
from stack.dope.net import N_AFFINITY, N_BELIEF, STRIDE, FoldedDopeNet, load_weights, set_memory_order
from stack import metrics
from stack.config import torch_threads
from stack.errors import DopeSlamError
from stack.dope.targets import to_input_px
from stack.messages import CameraFrame, Detection

log = logging.getLogger(__name__)

WEIGHTS_DIR = Path(__file__).parent / "weights"
WINDOW_MIN_PIXELS = 40  # default of DopeDetector(window_min_pixels=...): depth windows holding fewer are skipped
MEAN, STD = 0.5, 0.25  # as in training (stack.dope.train)


PRECISIONS = ("fp32", "bf16", "int8")
REFINEMENT_ORDERS = ("auto", "channels_last", "contiguous")
DEFAULT_PRECISION = "fp32"


def bf16_native(device="cpu") -> bool:
    """Whether ``device`` runs bfloat16 convolutions natively (a CUDA device, or a CPU with AVX512-BF16 or
    AMX that oneDNN uses); elsewhere bfloat16 is emulated and slower than fp32."""
    if torch.device(device).type == "cuda":
        return True
    try:
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def effective_precision(precision: str = DEFAULT_PRECISION, device="cpu") -> str:
    """The precision a detector asked for ``precision`` runs in on ``device``: bf16 only where it is native,
    int8 only on a CPU with PyTorch's quantised kernels; elsewhere fp32."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision == "bf16":
        return "bf16" if bf16_native(device) else "fp32"
    if precision == "int8":
        from stack.dope import int8

        return "int8" if torch.device(device).type == "cpu" and int8.available() else "fp32"
    return "fp32"


def refinement_memory_order(order: str = "auto", channels_last: bool = True, device="cpu") -> str:
    """The memory order the network's refinement stages run in, for ``order`` ("auto", "channels_last" or
    "contiguous"). ``"auto"``: the plain (contiguous) order on a CPU whose widest vector unit PyTorch uses
    is AVX2, where oneDNN's 7x7 convolutions of 32 channels run faster in it (the network takes about 8 %
    less time: docs/speed.md, "The refinement stages in the plain memory order"); elsewhere the order of
    ``channels_last``."""
    if order not in REFINEMENT_ORDERS:
        raise ValueError(f"refinement_order must be one of {', '.join(REFINEMENT_ORDERS)}, got {order!r}")
    if order != "auto":
        return order
    if torch.device(device).type == "cpu" and torch.backends.cpu.get_cpu_capability() == "AVX2":
        return "contiguous"
    return "channels_last" if channels_last else "contiguous"


def default_weights(input_mode: str = "rgb") -> Path:
    """The shipped weights for ``input_mode`` ('rgb' or 'depth')."""
    if input_mode not in ("rgb", "depth"):
        raise ValueError(f"input must be 'rgb' or 'depth', got {input_mode!r}")
    return WEIGHTS_DIR / f"dope_{input_mode}.pt"


def default_colour_model_path() -> Path:
    return WEIGHTS_DIR / "hog_colour.json"


def default_thresholds_path(input_mode: str = "rgb") -> Path:
    return WEIGHTS_DIR / f"fpr_thresholds_{input_mode}.json"


def cuboid_points(dims) -> np.ndarray:
    """(9, 3) cuboid corners + centroid in DOPE order in the object frame (x right, y top, z front)."""
    return metrics.cuboid_points(dims, "keypoints")


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# --- peaks, association, PnP --------------------------------------------------------------------

def max_3x3(maps: np.ndarray) -> np.ndarray:
    """The maximum over each element's 3x3 neighbourhood in each 2D map of ``maps`` (..., h, w), nothing
    beyond the edges: ``scipy.ndimage.maximum_filter`` with size (1, ..., 3, 3), mode constant and cval
    -inf, the same values, as six elementwise maxima (a row pass, then a column pass) in a fifth of its
    time on the network's maps. Maps with NaN go through SciPy, whose NaN handling this does not copy."""
    if maps.dtype.kind != "f" or np.isnan(maps).any():
        size = (1,) * (maps.ndim - 2) + (3, 3)
        return maximum_filter(maps, size=size, mode="constant", cval=-np.inf)
    h, w = maps.shape[-2:]
    pad = np.full(maps.shape[:-2] + (h + 2, w + 2), -np.inf, dtype=maps.dtype)
    pad[..., 1:-1, 1:-1] = maps
    rows = np.maximum(pad[..., :-2], pad[..., 1:-1])
    np.maximum(rows, pad[..., 2:], out=rows)  # (..., h + 2, w): each row's 3-wide maxima
    out = np.maximum(rows[..., :-2, :], rows[..., 1:-1, :])
    return np.maximum(out, rows[..., 2:, :], out=out)


def local_maxima(maps: np.ndarray, threshold: float) -> np.ndarray:
    """Where each 2D map of ``maps`` (..., h, w) has a local maximum (3x3) above ``threshold``: bool, same shape."""
    return (maps == max_3x3(maps)) & (maps > threshold)


def find_peaks(belief: np.ndarray, threshold: float, smooth_sigma: float = 0.0) -> list[tuple[int, int, float]]:
    """Local maxima (3x3) of a 2D map above ``threshold``: [(row, col, value)], strongest first."""
    m = belief
    if smooth_sigma > 0:
        m = cv2.GaussianBlur(belief.astype(np.float32), (0, 0), smooth_sigma)
    return [q[:3] for q in map_peaks(m[None], threshold, refine=False)[0]]


def map_peaks(maps: np.ndarray, threshold: float, belief: np.ndarray | None = None,
              refine: bool = True) -> list[list[tuple]]:
    """The peaks of each map of ``maps`` (n, h, w), as :func:`find_peaks` finds them (a plateau once,
    strongest first): per map [(row, col, value, x, y)], (x, y) refined by :func:`refine_peak` on
    ``belief`` (default: the maps themselves; without ``refine``, (row, col, value) only). All maps'
    peaks are found, and refined, in one pass."""
    out: list[list[tuple]] = [[] for _ in range(len(maps))]
    mi, rows, cols = np.nonzero(local_maxima(maps, threshold))
    if len(mi) == 0:
        return out
    vals = maps[mi, rows, cols]
    for i in np.lexsort((-vals, mi)):  # per map, strongest first; ties in row-major order
        k, r, c = int(mi[i]), int(rows[i]), int(cols[i])
        if any(abs(r - q[0]) <= 1 and abs(c - q[1]) <= 1 for q in out[k]):
            continue  # a plateau (equal neighbours) is one peak
        out[k].append((r, c, float(vals[i])))
    if refine:  # at least one peak was kept (each map with a candidate keeps its strongest)
        found = [(k, q[0], q[1]) for k, peaks in enumerate(out) for q in peaks]
        xy = iter(refine_peaks(maps if belief is None else belief, *zip(*found)))
        out = [[q + next(xy) for q in peaks] for peaks in out]
    return out


def refine_peak(belief: np.ndarray, row: int, col: int, r: int = 1) -> tuple[float, float]:
    """(x, y) sub-cell peak: belief-weighted centroid of the (2r+1)^2 window, negatives clipped."""
    h, w = belief.shape
    y0, y1, x0, x1 = max(0, row - r), min(h, row + r + 1), max(0, col - r), min(w, col + r + 1)
    win = np.clip(belief[y0:y1, x0:x1], 0, None).astype(np.float64)
    s = win.sum()
    if s <= 1e-12:
        return float(col), float(row)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    return float((win * xx).sum() / s), float((win * yy).sum() / s)


def refine_peaks(maps: np.ndarray, index, rows, cols, r: int = 1) -> list[tuple[float, float]]:
    """:func:`refine_peak` of ``maps[index[i]]`` at (rows[i], cols[i]) for each i, the same bits: the
    windows that lie inside their map in one pass (each window summed on its own, in the same order)."""
    index, rows, cols = (np.asarray(v, dtype=np.intp) for v in (index, rows, cols))
    out: list[tuple[float, float] | None] = [None] * len(rows)
    h, w = maps.shape[1:]
    inner = np.nonzero((rows >= r) & (rows < h - r) & (cols >= r) & (cols < w - r))[0]
    if len(inner):
        ri, ci = rows[inner], cols[inner]
        off = np.arange(-r, r + 1, dtype=np.intp)
        yy = np.repeat(ri[:, None] + off, 2 * r + 1, axis=1)  # row-major window order, as np.mgrid's
        xx = np.tile(ci[:, None] + off, (1, 2 * r + 1))
        win = np.clip(maps[index[inner][:, None], yy, xx], 0, None).astype(np.float64)
        s, sx, sy = win.sum(axis=1), (win * xx).sum(axis=1), (win * yy).sum(axis=1)
        for j, i in enumerate(inner):
            out[i] = (float(ci[j]), float(ri[j])) if s[j] <= 1e-12 else (float(sx[j] / s[j]), float(sy[j] / s[j]))
    for i in range(len(rows)):
        if out[i] is None:
            out[i] = refine_peak(maps[index[i]], int(rows[i]), int(cols[i]), r)
    return out


@dataclass
class RawObject:
    """Key points of one object instance found in one class's maps (output-grid coordinates)."""

    points: np.ndarray  # (9, 2) x, y in output cells, NaN where missing
    scores: np.ndarray  # (9,)


def associate(belief: np.ndarray, affinity: np.ndarray, peak_threshold: float = 0.1,
              angle_threshold: float = 0.5, smooth_sigma: float = 0.0, min_corners: int = 4,
              peaks: list | None = None) -> list[RawObject]:
    """Group corner peaks to centroid peaks via the affinity fields (one class: belief (9,h,w), affinity (16,h,w)).

    A corner joins the centroid whose direction from the corner is within ``angle_threshold`` radians
    of the corner's affinity vector; among those, the nearest in angle (ties: nearer in distance).
    Per centroid and corner the strongest peak is kept. Objects with fewer than ``min_corners``
    corners are dropped. ``peaks``: :func:`map_peaks` of the 9 maps (smoothed by ``smooth_sigma``
    when it is above 0, refined on ``belief``), when the caller has them already.
    """
    if peaks is None:
        maps = belief
        if smooth_sigma > 0:
            maps = np.stack([cv2.GaussianBlur(m.astype(np.float32), (0, 0), smooth_sigma) for m in belief])
        peaks = map_peaks(maps, peak_threshold, belief)
    if not peaks[8]:
        return []
    objs = []
    for r, c, v, x, y in peaks[8]:
        pts = np.full((9, 2), np.nan)
        sc = np.zeros(9)
        pts[8] = (x, y)
        sc[8] = v
        objs.append((pts, sc))
    cpos = np.array([o[0][8] for o in objs])
    for k in range(8):
        for r, c, v, x, y in peaks[k]:
            vec = affinity[2 * k:2 * k + 2, r, c].astype(np.float64)
            nv = math.sqrt(vec.dot(vec))  # np.linalg.norm's own arithmetic, without its checks
            d = cpos - np.array([x, y])
            dist = np.sqrt(np.add.reduce(d * d, axis=1))  # np.linalg.norm(d, axis=1), the same way
            if nv < 1e-3:
                # no direction (corner on top of the centroid): accept the nearest centre if very close
                best = int(np.argmin(dist))
                if dist[best] > 1.0:
                    continue
            else:
                cosang = (d @ (vec / nv)) / np.maximum(dist, 1e-6)
                ang = np.arccos(np.minimum(np.maximum(cosang, -1.0), 1.0))
                ang[dist < 0.5] = 0.0
                ok = (ang <= angle_threshold).nonzero()[0]
                if len(ok) == 0:
                    continue
                best = int(ok[np.lexsort((dist[ok], ang[ok].round(2)))[0]])
            pts, sc = objs[best]
            if v > sc[k]:
                pts[k] = (x, y)
                sc[k] = v
    out = []
    for pts, sc in objs:
        if np.sum(np.isfinite(pts[:8, 0])) >= min_corners:
            out.append(RawObject(pts, sc))
    return out


def solve_pose(keypoints_px: np.ndarray, dims, K: np.ndarray) -> tuple[np.ndarray, float] | None:
    """T_cam_obj (4x4) from (9, 2) key points (NaN = missing) and the cuboid; with the RMS reprojection error.

    EPnP for the initial estimate, then iterative (Levenberg-Marquardt) refinement. None when fewer
    than 5 key points or the solution is behind the camera.
    """
    obj = cuboid_points(dims)
    ok = np.all(np.isfinite(keypoints_px), axis=1)
    if ok.sum() < 5:
        return None
    P = obj[ok].astype(np.float64)
    uv = keypoints_px[ok].astype(np.float64)
    K = np.asarray(K, dtype=np.float64)
    success, rvec, tvec = cv2.solvePnP(P, uv, K, None, flags=cv2.SOLVEPNP_EPNP)
    if not success:
        return None
    if tvec[2, 0] <= 0:
        success, rvec, tvec = cv2.solvePnP(P, uv, K, None, flags=cv2.SOLVEPNP_SQPNP) if hasattr(cv2, "SOLVEPNP_SQPNP") \
            else (False, None, None)
        if not success or tvec[2, 0] <= 0:
            return None
    rvec, tvec = cv2.solvePnPRefineLM(P, uv, K, None, rvec, tvec)
    if tvec[2, 0] <= 0:
        return None
    proj, _ = cv2.projectPoints(P, rvec, tvec, K, None)
    err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - uv) ** 2, axis=1))))
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T, err


def silhouette_crop(dims, T_cam_obj: np.ndarray, K, width: int, height: int) -> tuple[tuple[int, int], np.ndarray] | None:
    """A cuboid's silhouette (the convex hull of its 8 projected corners) within its bounding box in a
    ``width`` x ``height`` image: ((row, col) of the box, boolean mask of the box), the same pixels as
    drawing it into the whole image; None when it misses the image or reaches behind the camera."""
    P = cuboid_points(dims)[:8]
    Xc = P @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    if np.any(Xc[:, 2] <= 1e-3):
        return None
    uv = Xc @ np.asarray(K, dtype=float).T
    uv = uv[:, :2] / uv[:, 2:]
    hull = cv2.convexHull(np.round(uv).astype(np.int32))
    lo, hi = hull.reshape(-1, 2).min(axis=0), hull.reshape(-1, 2).max(axis=0)
    if np.any(np.abs(np.concatenate([lo, hi])) > 1 << 20):  # far outside: drawn into the whole image
        mask = np.zeros((height, width), np.uint8)
        cv2.fillConvexPoly(mask, hull, 1)
        return (0, 0), mask.astype(bool)
    x0, y0 = max(0, int(lo[0])), max(0, int(lo[1]))
    x1, y1 = min(width, int(hi[0]) + 1), min(height, int(hi[1]) + 1)
    if x1 <= x0 or y1 <= y0:
        return None
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, hull - np.array([x0, y0], dtype=np.int32), 1)
    return (y0, x0), mask.astype(bool)


# --- FPR -----------------------------------------------------------------------------------------

def belief_sum(belief_cls: np.ndarray) -> float:
    """FPR's quantity: the sum of one class's belief tensor (9 maps), negative values clipped."""
    return float(np.clip(belief_cls, 0, None).sum())


def calibrate_threshold(scores, correct, target_precision: float = 0.995, n_positives: int | None = None,
                        fallback: bool = False, fallback_recall: float = 0.6, min_passed: int = 20,
                        min_recall: float = 0.0) -> dict:
    """The belief-sum threshold with the largest recall whose precision is at least ``target_precision``.

    ``scores``: belief sums of a calibration set's predictions; ``correct``: whether each is a true
    detection. A prediction passes when its score <= threshold. A cut counts as meeting the target
    only when at least ``min_passed`` predictions pass it (a handful of lucky ones proves nothing).
    A cut meets the target only if it also keeps at least ``min_recall`` of the correct predictions
    (the paper's D6F target is 99.5 % precision with at least 60 % recall: a cut that throws away most
    true detections to please one false one has not met it).
    Recall is passed-correct over ``n_positives`` (default: all correct predictions). Cuts are only
    placed between distinct scores.
    Returns {threshold, precision, recall, passed, target_met}. When no cut reaches the target the
    threshold is -inf (nothing passes), or with ``fallback`` the cut of highest precision among those
    keeping at least ``fallback_recall`` of the correct predictions (``target_met`` False).
    """
    s = np.asarray(scores, dtype=float)
    c = np.asarray(correct, dtype=bool)
    if s.shape != c.shape:
        raise ValueError(f"scores ({s.shape}) and correct ({c.shape}) differ in shape")
    n_pos = int(c.sum()) if n_positives is None else int(n_positives)
    best = {"threshold": -math.inf, "precision": 1.0, "recall": 0.0, "passed": 0, "target_met": True}
    if len(s) == 0:
        return best
    order = np.argsort(s, kind="stable")
    s, c = s[order], c[order]
    tp = np.cumsum(c)
    n = np.arange(1, len(s) + 1)
    prec = tp / n
    last_of_value = np.r_[s[1:] != s[:-1], True]  # cut only after the last of equal scores
    for i in np.nonzero(last_of_value & (prec >= target_precision) & (n >= min(min_passed, len(s))))[0]:
        rec = tp[i] / max(n_pos, 1)
        if rec < min_recall:
            continue
        if rec > best["recall"] or (rec == best["recall"] and best["passed"] == 0):
            nxt = s[i + 1] if i + 1 < len(s) else s[i] + 1.0
            best = {"threshold": float(0.5 * (s[i] + nxt)), "precision": float(prec[i]), "recall": float(rec),
                    "passed": int(n[i]), "target_met": True}
    if best["passed"] == 0 and fallback and n_pos > 0:
        ok = np.nonzero(last_of_value & (tp >= max(1, fallback_recall * n_pos)))[0]
        if len(ok):
            i = int(ok[np.lexsort((-tp[ok], -prec[ok]))[0]])
            nxt = s[i + 1] if i + 1 < len(s) else s[i] + 1.0
            best = {"threshold": float(0.5 * (s[i] + nxt)), "precision": float(prec[i]),
                    "recall": float(tp[i] / n_pos), "passed": int(n[i]), "target_met": False}
    return best


class ThresholdsError(DopeSlamError, ValueError):
    """An FPR threshold file that is missing or is not one (its path and what was expected)."""


@dataclass
class FprThresholds:
    """Belief-sum thresholds per class and stage count ({cls: {stages: threshold}}), with overrides."""

    table: dict = field(default_factory=dict)
    default: float = math.inf  # used where the table has no entry
    overrides: dict = field(default_factory=dict)  # manual {cls: {stages: threshold}} or {cls: threshold}
    meta: dict = field(default_factory=dict)

    def get(self, cls: str, stages: int) -> float:
        o = self.overrides.get(cls)
        if isinstance(o, (int, float)):
            return float(o)
        if isinstance(o, dict) and str(stages) in {str(k) for k in o}:
            return float({str(k): v for k, v in o.items()}[str(stages)])
        row = self.table.get(cls, {})
        v = {str(k): x for k, x in row.items()}.get(str(stages))
        return self.default if v is None else float(v)

    def passes(self, cls: str, stages: int, score: float) -> bool:
        return score <= self.get(cls, stages)

    def set(self, cls: str, stages: int, threshold: float) -> None:
        self.overrides.setdefault(cls, {})
        if not isinstance(self.overrides[cls], dict):
            self.overrides[cls] = {}
        self.overrides[cls][str(stages)] = float(threshold)

    @staticmethod
    def calibrate(records, target_precision: float = 0.995, meta: dict | None = None,
                  fallback: bool = True, min_recall: float = 0.6, fallback_recall: float = 0.95) -> "FprThresholds":
        """From records (cls, stages, belief_sum, correct): per (cls, stages) the threshold of
        :func:`calibrate_threshold`. Returns the table with per-entry precision/recall in ``meta``.

        Where the belief sum cannot reach ``target_precision`` with ``min_recall``, the fall-back cut
        keeps ``fallback_recall`` of the correct detections: a weak test should not throw away true
        detections that the depth and colour checks would let through."""
        groups: dict = {}
        for cls, stages, score, ok in records:
            groups.setdefault((str(cls), int(stages)), []).append((float(score), bool(ok)))
        table, stats = {}, {}
        for (cls, st), rows in sorted(groups.items()):
            sc, ok = zip(*rows)
            r = calibrate_threshold(sc, ok, target_precision, fallback=fallback, min_recall=min_recall,
                                    fallback_recall=fallback_recall)
            table.setdefault(cls, {})[str(st)] = r["threshold"]
            stats.setdefault(cls, {})[str(st)] = {**r, "n": len(rows), "n_correct": int(sum(ok))}
        return FprThresholds(table, math.inf, {}, {"target_precision": target_precision, "min_recall": min_recall,
                                                   "fallback_recall": fallback_recall, "stats": stats, **(meta or {})})

    def save(self, path) -> None:
        path = Path(path)
        enc = lambda t: {c: {s: (None if not math.isfinite(v) else v) if v != -math.inf else "-inf"  # noqa: E731
                             for s, v in row.items()} for c, row in t.items()}
        blob = {"table": enc(self.table), "default": None if math.isinf(self.default) else self.default,
                "overrides": self.overrides, "meta": self.meta}
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            json.dump(blob, f, indent=1)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)

    @staticmethod
    def load(path) -> "FprThresholds":
        try:
            with open(path) as f:
                blob = json.load(f)
        except FileNotFoundError:
            raise ThresholdsError(f"{path}: FPR threshold file not found") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ThresholdsError(f"{path}: not valid JSON ({exc})") from None
        except IsADirectoryError:
            raise ThresholdsError(f"{path}: is a folder; expected an FPR threshold file (JSON)") from None
        if not isinstance(blob, dict) or "table" not in blob:
            raise ThresholdsError(f"{path}: expected a 'table' field ({{cls: {{stages: threshold}}}})")

        def dec(v):
            return -math.inf if v == "-inf" else (math.inf if v is None else float(v))
        try:
            table = {str(c): {s: dec(v) for s, v in row.items()} for c, row in blob["table"].items()}
            default = math.inf if blob.get("default") is None else float(blob["default"])
        except (AttributeError, TypeError, ValueError) as exc:
            raise ThresholdsError(f"{path}: 'table' must map each class to {{stages: threshold or null}} "
                                  f"and 'default' be a number ({exc})") from None
        return FprThresholds(table, default, blob.get("overrides", {}), blob.get("meta", {}))


# --- the detector --------------------------------------------------------------------------------

class DopeDetector:
    """DOPE + FPR on camera frames: ``detect(frame) -> list[Detection]`` (every stage count at once
    with ``detect_stages``). Every detection is returned with its FPR verdict in ``fpr_pass``; with
    ``fpr=False`` all pass.

    weights: path (None = shipped default for ``input``); input: 'rgb' or 'depth'; stages: 1..6;
    dims: {cls: (3,) cuboid size} (required: the stack does not read the simulator's catalogue);
    thresholds: FprThresholds, a JSON path, or None (= the shipped file beside the weights);
    depth_windows: [(near, far), ...] metres for depth input (None = sliding 0.3-1.8 m windows of
    0.3 m overlapping 0.1 m).
    window_min_pixels (depth input): a window runs through the network only when at least this many
    sampled pixels (every second row and column at 640x480, every pixel at 320x240) inside it stand
    above the floor, which is fitted to the frame's depth (:func:`stack.dope.depth_window.window_content`;
    no floor found: every window runs).
    A window that holds only floor (and what is beyond it) costs a network pass and finds nothing but
    false positives. 0 runs every window.
    depth_refine: slide each detection along its viewing ray to fit the frame's aligned depth
    (:mod:`stack.dope.depth_refine`) when the frame has depth; the PnP-only pose is kept in
    ``extra['pnp_pose']``, the fit in ``extra['depth_fit']``.
    threads: torch threads (None: the environment variable DOPESLAM_TORCH_THREADS, else torch's
    default). On cores shared with other busy processes one thread is often 2x faster than two.
    depth_check (with FPR on and depth_refine): a detection whose cuboid the depth image does not
    support (too few consistent depth pixels, see :func:`stack.dope.depth_refine.refine_translation`) fails
    FPR (``extra['fpr_rejected_by'] = 'depth'``), whatever its belief sum.
    colour_check (with FPR on, RGB frames with light): a detection whose silhouette's colours fit
    another class's colour model better (by more than ``colour_margin``), or fit its own class's model
    worse than that class's threshold, fails FPR (``extra['fpr_rejected_by'] = 'colour'``); ``colour``:
    a ColourModel or JSON path (None = ``stack/weights/hog_colour.json``). Frames darker than
    ``min_colour_brightness`` (mean 0-255 in the silhouette) skip the check: colour says nothing there.
    shape_check (depth input): a detection whose object's depth another class's cuboid explains
    clearly better (own residual above ``shape_min_residual_m`` metres and ``shape_ratio`` times the
    best other class's, :func:`stack.dope.shape_check.shape_verdict`) fails FPR when FPR is on
    (``extra['fpr_rejected_by'] = 'shape'``); the verdict is in ``extra['shape']``.
    channels_last: run the network with its weights and input in channels-last memory order (on a CPU,
    about 15 % less time per image: docs/speed.md); the maps differ from the default order's in the last
    float bits only.
    refinement_order: the memory order of the refinement stages (stages 2-6, 7x7 convolutions, three
    quarters of the multiply-adds): ``"channels_last"``, ``"contiguous"`` or ``"auto"`` (the default:
    contiguous on an AVX2 CPU, where it is faster, else as ``channels_last``;
    :func:`refinement_memory_order`); :attr:`refinement_order` is what runs. The maps differ in the last
    float bits only.
    fold_stages: run each refinement stage's first convolution on the previous stage's last hidden layer
    in place of its maps (:class:`stack.dope.net.FoldedDopeNet`: about a fifth fewer multiply-adds); the
    maps differ in the last float bits only.
    precision: ``"fp32"`` (the default): float32 throughout. ``"bf16"``: the network's weights and input
    in bfloat16, its maps back in float32 for decoding; on a CPU with native bfloat16 (AVX512-BF16 or AMX)
    it halves the network's time, and the maps differ from fp32's by up to about 0.02 in belief
    (docs/speed.md has its effect on whole maps: faster, and not always the same labels). Where the CPU
    has no native bfloat16 it runs in fp32 and says so in the log. ``"int8"``: the folded network's
    convolution blocks in 8-bit integers (:mod:`stack.dope.int8`, needs ``fold_stages``), at the activation
    scales of the calibration beside the weights (``NAME_int8.json``, from ``dopeslam calibrate-int8``); the
    output layers stay float32. On a CPU it takes a fifth to a quarter off the network's time; the maps differ
    from fp32's by up to about 0.2 in belief (docs/speed.md has its effect on whole maps). :attr:`precision`
    is what runs.
    """

    def __init__(self, weights=None, input: str = "rgb", stages: int = 6, fpr: bool = True, dims: dict | None = None,
                 thresholds=None, input_size: tuple[int, int] = (320, 240), peak_threshold: float = 0.3,
                 angle_threshold: float = 0.5, min_corners: int = 4, max_reproj_px: float = 12.0,
                 depth_windows=None, device: str | None = None, threads: int | None = None,
                 depth_refine: bool = True, depth_check: bool = True, colour_check: bool = True,
                 colour=None, colour_margin: float = 0.0, min_colour_brightness: float = 20.0,
                 window_min_pixels: int = WINDOW_MIN_PIXELS, shape_check: bool = True,
                 shape_min_residual_m: float = 0.006, shape_ratio: float = 1.5, channels_last: bool = True,
                 precision: str = DEFAULT_PRECISION, fold_stages: bool = True, refinement_order: str = "auto"):
        if input not in ("rgb", "depth"):
            raise ValueError(f"input must be 'rgb' or 'depth', got {input!r}")
        if not dims:
            raise ValueError("DopeDetector needs dims={cls: (w, h, d)} for the cuboids of the classes it detects")
        self.input = input
        self.weights_path = Path(weights) if weights is not None else default_weights(input)
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        if threads is None:
            threads = torch_threads()  # DOPESLAM_TORCH_THREADS (stack.config); a bad value: ConfigError
        if threads:
            torch.set_num_threads(threads)
        self.model, self.weights_extra = load_weights(self.weights_path, self.device)
        self.fold_stages = bool(fold_stages)
        if self.fold_stages:
            self.model = FoldedDopeNet(self.model)
        self.channels_last = bool(channels_last)
        self.refinement_order = refinement_memory_order(refinement_order, self.channels_last, self.device)
        set_memory_order(self.model, self.channels_last, self.refinement_order == "channels_last")
        self.precision = effective_precision(precision, self.device)  # what runs
        if self.precision != precision:
            log.warning("precision %s: %s; the network runs in fp32", precision,
                        "this CPU has no native bfloat16 (AVX512-BF16 or AMX)" if precision == "bf16"
                        else "int8 runs on a CPU with PyTorch's quantised kernels only")
        self._dtype = torch.bfloat16 if self.precision == "bf16" else torch.float32
        self.int8_calibration: Path | None = None
        if self.precision == "int8":
            self._to_int8(input_size)
        elif self._dtype != torch.float32:
            self.model = self.model.to(self._dtype)
        self.classes = tuple(self.model.classes)
        if not 1 <= stages <= self.model.config.stages:
            raise ValueError(f"stages must be 1..{self.model.config.stages}, got {stages}")
        self.stages = int(stages)
        self.fpr = bool(fpr)
        self.dims = {c: np.asarray(d, dtype=float) for c, d in dims.items()}
        self.input_size = tuple(input_size)
        self.peak_threshold = peak_threshold
        self.angle_threshold = angle_threshold
        self.min_corners = min_corners
        self.max_reproj_px = max_reproj_px
        self.depth_refine = bool(depth_refine)
        self.depth_check = bool(depth_check)
        self.depth_windows = list(depth_windows) if depth_windows else sliding_windows(0.3, 1.8, 0.3, 0.1)
        self.window_min_pixels = int(window_min_pixels)
        self.windows_run = 0  # depth windows run through the network, and those skipped (counters)
        self.windows_skipped = 0
        self.colour_check = bool(colour_check) and input == "rgb"
        self.colour_margin = float(colour_margin)
        self.min_colour_brightness = float(min_colour_brightness)
        self.colour: ColourModel | None = None
        self.shape_check = bool(shape_check) and input == "depth"
        self.shape_min_residual_m = float(shape_min_residual_m)
        self.shape_ratio = float(shape_ratio)
        if self.colour_check:
            self.colour = colour if isinstance(colour, ColourModel) else ColourModel.load(
                colour if colour is not None else default_colour_model_path())
        self.thresholds_path: Path | None = None  # the thresholds' file, when they came from one
        if isinstance(thresholds, FprThresholds):
            self.thresholds = thresholds
        elif thresholds is not None:
            self.thresholds = FprThresholds.load(thresholds)
            self.thresholds_path = Path(thresholds)
        else:
            p = self.weights_path.parent / f"fpr_thresholds_{input}.json"
            self.thresholds_path = p if p.exists() else None
            self.thresholds = FprThresholds.load(p) if p.exists() else FprThresholds()
            if not p.exists() and fpr:
                log.warning("no FPR thresholds beside %s: FPR passes everything until calibrated", self.weights_path)

    def _to_int8(self, input_size) -> None:
        """The folded network's convolution blocks in int8, at the calibration beside the weights."""
        from stack.dope import int8

        if not self.fold_stages:
            raise ValueError("precision int8 runs the folded network: fold_stages must be on")
        self.int8_calibration = int8.calibration_path(self.weights_path)
        calibration = int8.load(self.int8_calibration)
        made_for = calibration["meta"].get("weights_sha256")  # load() checked its type
        if made_for is not None and made_for != file_sha256(self.weights_path):
            raise int8.Int8Error(f"{self.int8_calibration}: calibrated for other weights than {self.weights_path} "
                                 f"(run dopeslam calibrate-int8 --weights {self.weights_path})")
        w, h = input_size
        example = torch.zeros((1, 3, int(h), int(w)))
        self.model = int8.quantize(set_memory_order(self.model, False, False), calibration, example,
                                   source=self.int8_calibration)
        self.channels_last = False  # the int8 kernels take the plain order as fast
        self.refinement_order = "contiguous"

    # network input -------------------------------------------------------------------------------
    def _inputs(self, frame: CameraFrame) -> tuple[np.ndarray, list]:
        """(N, 3, h, w) network inputs and, per input, the depth window (None for RGB)."""
        w, h = self.input_size
        if self.input == "rgb":
            if frame.rgb is None:
                raise ValueError("DopeDetector(input='rgb') got a CameraFrame without rgb")
            img = frame.rgb
            if img.shape[1] != w or img.shape[0] != h:
                img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            x = ((img.astype(np.float32) / 255.0 - MEAN) / STD).transpose(2, 0, 1)
            return x[None], [None]
        if frame.depth_m is None:
            raise ValueError("DopeDetector(input='depth') got a CameraFrame without depth_m")
        windows = list(self.depth_windows)
        if self.window_min_pixels > 0:
            # every second pixel at 640x480, every pixel at 320x240: the counts mean the same at any size
            step = max(1, int(round(frame.info.width / 320)))
            counts = window_content(frame.depth_m, np.asarray(frame.info.K, dtype=float), windows, step=step)
            windows = [win for win, n in zip(windows, counts) if n >= self.window_min_pixels]
        self.windows_run += len(windows)
        self.windows_skipped += len(self.depth_windows) - len(windows)
        if not windows:
            return np.zeros((0, 3, h, w), np.float32), []
        d = frame.depth_m
        if d.shape[1] != w or d.shape[0] != h:
            d = cv2.resize(d, (w, h), interpolation=cv2.INTER_NEAREST)
        xs = []
        for near, far in windows:
            img = preprocess_depth(d, near, far)
            xs.append(np.repeat(((img - MEAN) / STD)[None], 3, axis=0))
        return np.stack(xs).astype(np.float32), windows

    @torch.inference_mode()
    def _forward(self, x: np.ndarray, stages: int, last_only: bool = False):
        """Each stage's (belief, affinity) maps as float32 arrays, or only the last stage's
        (``last_only``: the others are not copied out)."""
        xt = torch.from_numpy(x).to(self.device, self._dtype)
        if self.channels_last:
            xt = xt.contiguous(memory_format=torch.channels_last)
        out = self.model(xt, stages)
        if last_only:
            out = out[-1:]
        return [(b.float().cpu().contiguous().numpy(), a.float().cpu().contiguous().numpy()) for b, a in out]

    # decoding ------------------------------------------------------------------------------------
    def _decode(self, belief: np.ndarray, affinity: np.ndarray, frame: CameraFrame, stages: int,
                window) -> list[Detection]:
        """Detections from one input's maps (belief (C*9,h,w), affinity (C*16,h,w)) at one stage count."""
        dets = []
        # with depth to fit to, a depth window's range check waits for the fitted range: PnP's range of a
        # small object is often tens of centimetres off (its corners a pixel or two apart at 320x240)
        refine_later = self.depth_refine and frame.depth_m is not None
        W, H = frame.info.width, frame.info.height
        sx, sy = W / self.input_size[0], H / self.input_size[1]
        peaks = map_peaks(belief, self.peak_threshold)  # every class's maps in one pass
        for ci, cls in enumerate(self.classes):
            if cls not in self.dims:
                continue
            b = belief[ci * N_BELIEF:(ci + 1) * N_BELIEF]
            a = affinity[ci * N_AFFINITY:(ci + 1) * N_AFFINITY]
            if b[8].max() <= self.peak_threshold:
                continue
            bsum = belief_sum(b)
            for obj in associate(b, a, self.peak_threshold, self.angle_threshold, min_corners=self.min_corners,
                                 peaks=peaks[ci * N_BELIEF:(ci + 1) * N_BELIEF]):
                uv_in = to_input_px(obj.points, STRIDE)
                uv = np.stack([(uv_in[:, 0] + 0.5) * sx - 0.5, (uv_in[:, 1] + 0.5) * sy - 0.5], axis=1)
                sol = solve_pose(uv, self.dims[cls], frame.info.K)
                if sol is None:
                    continue
                T, err = sol
                if err > self.max_reproj_px * sx:
                    continue
                if window is not None and not refine_later and not self._in_window(T, window):
                    continue
                passed = (not self.fpr) or self.thresholds.passes(cls, stages, bsum)  # + depth check later
                dets.append(Detection(cls=cls, stamp=frame.stamp, T_cam_obj=T, keypoints_px=uv,
                                      peak_scores=obj.scores.copy(), belief_sum=bsum, stages=stages, fpr_pass=passed,
                                      extra={"reproj_px": err, "n_keypoints": int(np.isfinite(uv[:, 0]).sum()),
                                             "input": self.input, "window": window}))
        return dets

    @staticmethod
    def _in_window(T: np.ndarray, window, margin_m: float = 0.05) -> bool:
        return window[0] - margin_m <= T[2, 3] <= window[1] + margin_m

    def _window_filter(self, dets: list[Detection]) -> list[Detection]:
        """Detections of a depth window whose (depth-fitted) range lies in that window."""
        return [d for d in dets if d.extra.get("window") is None or self._in_window(d.T_cam_obj, d.extra["window"])]

    @staticmethod
    def _dedupe(dets: list[Detection], radius_m: float = 0.05) -> list[Detection]:
        """One detection per (class, place) across depth windows: the lowest belief sum wins."""
        out: list[Detection] = []
        for d in sorted(dets, key=lambda d: d.belief_sum):
            if any(o.cls == d.cls and np.linalg.norm(o.T_cam_obj[:3, 3] - d.T_cam_obj[:3, 3]) < radius_m for o in out):
                continue
            out.append(d)
        return out

    def _depth_refine(self, frame: CameraFrame, dets: list[Detection]) -> None:
        if not self.depth_refine or frame.depth_m is None:
            return
        for det in dets:
            fit = refine_translation(det.T_cam_obj, self.dims[det.cls], frame.info.K, frame.depth_m)
            det.extra["depth_fit"] = {"ok": fit.ok, "shift_m": fit.shift_m, "n_pixels": fit.n_pixels,
                                      "inlier_frac": fit.inlier_frac}
            if fit.ok:
                det.extra["pnp_pose"] = det.T_cam_obj
                det.T_cam_obj = fit.T_cam_obj
            elif self.fpr and self.depth_check:
                det.fpr_pass = False
                det.extra["fpr_rejected_by"] = "depth"

    def _colour_check(self, frame: CameraFrame, dets: list[Detection]) -> None:
        """Records ``extra['colour']`` for every detection; with FPR on, a failure fails FPR."""
        if not self.colour_check or frame.rgb is None:
            return
        for det in dets:
            if det.cls not in self.colour.models:
                continue
            crop = silhouette_crop(self.dims[det.cls], det.T_cam_obj, frame.info.K, frame.info.width,
                                   frame.info.height)
            if crop is None:
                continue
            (y0, x0), mask = crop
            if mask.sum() < 20:
                continue
            pix = frame.rgb[y0:y0 + mask.shape[0], x0:x0 + mask.shape[1]][mask]
            if float(pix.mean()) < self.min_colour_brightness:
                continue
            hist = colour_names(pix).mean(axis=0)
            dist = {c: self.colour.distance(c, hist) for c in self.colour.models}
            own = dist[det.cls]
            others = min((v for c, v in dist.items() if c != det.cls), default=math.inf)
            ok = own <= self.colour.thresholds[det.cls] and own <= others + self.colour_margin
            det.extra["colour"] = {"distance": own, "closest_other": others, "pass": bool(ok)}
            if not ok and self.fpr and det.fpr_pass:
                det.fpr_pass = False
                det.extra["fpr_rejected_by"] = "colour"

    def _shape_check(self, frame: CameraFrame, dets: list[Detection]) -> None:
        """Records ``extra['shape']`` for every detection still passing FPR; with FPR on, a failure fails FPR."""
        if not self.shape_check or frame.depth_m is None:
            return
        for det in dets:
            if not det.fpr_pass:
                continue
            v = shape_verdict(frame.depth_m, frame.info.K, det.T_cam_obj, self.dims, det.cls,
                              self.shape_min_residual_m, self.shape_ratio)
            if v is None:
                continue
            det.extra["shape"] = v.as_dict()
            if not v.ok and self.fpr:
                det.fpr_pass = False
                det.extra["fpr_rejected_by"] = "shape"

    def detect_stages(self, frame: CameraFrame, stage_counts=None) -> dict[int, list[Detection]]:
        """Detections for every stage count (default 1..configured stages) from one forward pass."""
        counts = sorted(stage_counts or range(1, self.stages + 1))
        x, windows = self._inputs(frame)
        if not windows:
            return {s: [] for s in counts}
        outs = self._forward(x, max(counts))
        result = {}
        for s in counts:
            b, a = outs[s - 1]
            dets = []
            for i, win in enumerate(windows):
                dets += self._decode(b[i], a[i], frame, s, win)
            result[s] = self._fit_and_filter(frame, dets, len(windows))
        return result

    def _fit_and_filter(self, frame: CameraFrame, dets: list[Detection], n_inputs: int) -> list[Detection]:
        """Depth fit, depth windows' range check, one detection per (class, place), colour and shape checks."""
        self._depth_refine(frame, dets)
        dets = self._window_filter(dets)
        dets = self._dedupe(dets) if n_inputs > 1 else dets
        self._colour_check(frame, dets)
        self._shape_check(frame, dets)
        return dets

    def detect(self, frame: CameraFrame) -> list[Detection]:
        """Detections (with FPR verdicts) of the configured stage count."""
        x, windows = self._inputs(frame)
        if not windows:
            return []
        b, a = self._forward(x, self.stages, last_only=True)[-1]
        dets = []
        for i, win in enumerate(windows):
            dets += self._decode(b[i], a[i], frame, self.stages, win)
        return self._fit_and_filter(frame, dets, len(windows))
