"""Scoring functions shared by the harness and the rosbag replay: odometry (ATE, RPE, TUM files),
per-detection pose error (ADD, ADD-S) and the paper's equations 3-8.

Odometry definitions (poses are 4x4 ``T_world_base`` at matching timestamps):

* ATE (absolute trajectory error): RMSE over poses of ``|t_est_i - t_gt_i|`` (metres), with the
  estimate placed in the ground-truth frame by a *given* alignment (the known start pose), or by the
  least-squares SE(3) alignment of Umeyama (1991) of the estimated positions onto the true ones. The
  latter is what ``evo_ape tum gt.txt est.txt -a`` prints as ``rmse``; the former what it prints
  without ``-a``.
* RPE (relative pose error) over a travelled distance ``delta_m``: for every pose i (but only the
  first of a run of poses where the robot stands still) take the first later pose j whose
  ground-truth path length from i is at least ``delta_m``; the relative error is
  ``E_ij = inv(inv(G_i) G_j) @ inv(P_i) P_j``. We report the mean over pairs of
  ``|t(E_ij)| / L_ij`` in percent (``trans_pct``) and of ``angle(E_ij) / L_ij`` in deg/m
  (``rot_deg_per_m``), with ``L_ij`` the true path length of the pair (>= delta_m, so a turn on the
  spot cannot divide by zero). RPE is invariant to the global alignment. (``evo_rpe --delta 1
  --delta_unit m --all_pairs`` differs: it takes j closest to ``delta_m``, by default along the
  *estimated* path, keeps every standing-still start, and reports metres, not a ratio.)
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from stack.errors import DopeSlamError
from stack.io import write_text
from stack.transforms import inv, make_T

# --------------------------------------------------------------------------------------------
# trajectories


def _positions(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"expected poses of shape (N, 4, 4), got {poses.shape}")
    return poses[:, :3, 3]


def _check_pair(est: np.ndarray, gt: np.ndarray) -> None:
    if np.shape(est) != np.shape(gt):
        raise ValueError(f"estimate and ground truth differ in shape: {np.shape(est)} vs {np.shape(gt)}")
    if len(est) == 0:
        raise ValueError("empty trajectory")


def ate_errors(T_world_est: np.ndarray, T_world_gt: np.ndarray, T_align: np.ndarray | None = None) -> np.ndarray:
    """Per-pose translation error (N,) in metres of ``T_align @ est`` against ``gt``."""
    _check_pair(T_world_est, T_world_gt)
    p_est = _positions(T_world_est)
    if T_align is not None:
        p_est = p_est @ T_align[:3, :3].T + T_align[:3, 3]
    return np.linalg.norm(p_est - _positions(T_world_gt), axis=1)


def ate_rmse(T_world_est: np.ndarray, T_world_gt: np.ndarray, T_align: np.ndarray | None = None) -> float:
    """ATE RMSE (m) with a given alignment (identity: the estimate is already in the ground-truth frame)."""
    e = ate_errors(T_world_est, T_world_gt, T_align)
    return float(np.sqrt(np.mean(e**2)))


def umeyama_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, float]:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991). Returns (4x4 [R|t], s).

    ``with_scale=False`` gives the SE(3) alignment (s = 1), as ``evo_ape -a``.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"expected two (N, 3) point sets, got {src.shape} and {dst.shape}")
    n = len(src)
    if n < 2:
        raise ValueError(f"Umeyama alignment needs at least 2 points, got {n}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # reflection: flip the weakest axis
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / np.mean(np.sum(xs**2, axis=1))) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return make_T(R, t), s


def ate_rmse_umeyama(T_world_est: np.ndarray, T_world_gt: np.ndarray) -> float:
    """ATE RMSE (m) after the best SE(3) alignment of the estimated positions onto the true ones."""
    _check_pair(T_world_est, T_world_gt)
    T_align, _ = umeyama_alignment(_positions(T_world_est), _positions(T_world_gt))
    return ate_rmse(T_world_est, T_world_gt, T_align)


@dataclass
class RPEResult:
    trans_pct: float  # mean |t(E)| / L * 100
    rot_deg_per_m: float  # mean angle(E) / L, degrees per metre
    pairs: int  # number of (i, j) pairs; 0 when the path is shorter than delta_m (values are NaN)
    delta_m: float


def path_length(T_world_gt: np.ndarray) -> np.ndarray:
    """Cumulative travelled distance (N,) along the positions, starting at 0."""
    p = _positions(T_world_gt)
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


STILL_M = 1e-3  # a ground-truth step shorter than this is standing still (RPE start poses)


def rpe(T_world_est: np.ndarray, T_world_gt: np.ndarray, delta_m: float = 1.0) -> RPEResult:
    """Relative pose error per travelled metre over segments of at least ``delta_m`` (see module doc)."""
    _check_pair(T_world_est, T_world_gt)
    if delta_m <= 0:
        raise ValueError(f"delta_m must be positive, got {delta_m}")
    est = np.asarray(T_world_est, dtype=float)
    gt = np.asarray(T_world_gt, dtype=float)
    dist = path_length(gt)
    j_of_i = np.searchsorted(dist, dist + delta_m, side="left")
    # one start per standing-still stretch: otherwise the pose where the robot sets off is the end of
    # every pair that starts while it waits, and its error alone would weigh as much as the whole drive
    moved = np.concatenate([[True], np.diff(dist) > STILL_M])
    valid = np.nonzero((j_of_i < len(dist)) & moved)[0]
    if len(valid) == 0:
        return RPEResult(float("nan"), float("nan"), 0, float(delta_m))
    trans, rot = [], []
    for i in valid:
        j = j_of_i[i]
        E = inv(inv(gt[i]) @ gt[j]) @ (inv(est[i]) @ est[j])
        L = dist[j] - dist[i]
        trans.append(np.linalg.norm(E[:3, 3]) / L)
        rot.append(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude()) / L)
    return RPEResult(float(100.0 * np.mean(trans)), float(np.mean(rot)), len(valid), float(delta_m))


# --------------------------------------------------------------------------------------------
# TUM trajectory files: one pose a line, "timestamp tx ty tz qx qy qz qw", '#' comments allowed


class TrajectoryFileError(DopeSlamError, ValueError):
    """A trajectory file that cannot be read; the message names the file, the line and what was expected."""


def write_tum(path: str | os.PathLike, stamps: np.ndarray, poses: np.ndarray) -> Path:
    """Write a TUM trajectory atomically (temp file in the same folder, then os.replace)."""
    path = Path(path)
    stamps = np.asarray(stamps, dtype=float)
    p = _positions(poses)
    if len(stamps) != len(p):
        raise ValueError(f"{len(stamps)} stamps for {len(p)} poses")
    q = Rotation.from_matrix(np.asarray(poses, dtype=float)[:, :3, :3]).as_quat() if len(p) else np.zeros((0, 4))
    lines = ["# timestamp tx ty tz qx qy qz qw\n"]
    lines += [f"{t:.9f} " + " ".join(_fixed(v) for v in (*xyz, *quat)) + "\n" for t, xyz, quat in zip(stamps, p, q)]
    write_text(path, "".join(lines))
    return path


def _fixed(v: float) -> str:
    """9 decimals, with no "-0.000000000" (a sign that only float noise decides)."""
    text = f"{v:.9f}"
    return text[1:] if text == "-0.000000000" else text


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: (stamps (N,), poses (N, 4, 4))."""
    path = Path(path)
    stamps, poses = [], []
    try:
        text = path.read_text()
    except OSError as exc:
        raise TrajectoryFileError(f"{path}: cannot read trajectory file ({exc.strerror})") from exc
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise TrajectoryFileError(
                f"{path}:{lineno}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got {len(fields)} fields")
        try:
            v = np.array([float(x) for x in fields])
        except ValueError as exc:
            raise TrajectoryFileError(f"{path}:{lineno}: expected numbers, got {line!r}") from exc
        qn = np.linalg.norm(v[4:8])
        if not np.all(np.isfinite(v)) or abs(qn - 1.0) > 1e-3:
            raise TrajectoryFileError(f"{path}:{lineno}: expected finite values and a unit quaternion (|q| = {qn:.6f})")
        stamps.append(v[0])
        poses.append(make_T(Rotation.from_quat(v[4:8] / qn).as_matrix(), v[1:4]))
    if stamps and np.any(np.diff(stamps) < 0):
        raise TrajectoryFileError(f"{path}: expected timestamps in increasing order")
    return np.array(stamps), np.array(poses).reshape(-1, 4, 4)


# --------------------------------------------------------------------------------------------
# per-detection pose error

# DOPE key point order; object frame x = right, y = top, z = front.
CUBOID_KEYPOINT_NAMES = ("FrontTopRight", "FrontTopLeft", "FrontBottomLeft", "FrontBottomRight",
                         "RearTopRight", "RearTopLeft", "RearBottomLeft", "RearBottomRight", "Center")
_CORNER_SIGNS = np.array([[+1, +1, +1], [-1, +1, +1], [-1, -1, +1], [+1, -1, +1],
                          [+1, +1, -1], [-1, +1, -1], [-1, -1, -1], [+1, -1, -1], [0, 0, 0]], dtype=float)


def cuboid_points(dims, kind: str = "keypoints", n: int = 1000, seed: int = 0) -> np.ndarray:
    """Model points of a cuboid of size ``dims`` (x y z) in its centroid frame.

    ``kind="keypoints"``: the 8 corners + centroid in DOPE order (9, 3).
    ``kind="surface"``: ``n`` points uniform over the surface (area-weighted faces), seeded.
    """
    d = np.asarray(dims, dtype=float).reshape(3)
    if np.any(d <= 0):
        raise ValueError(f"cuboid dims must be positive, got {d}")
    if kind == "keypoints":
        return _CORNER_SIGNS * d / 2.0
    if kind != "surface":
        raise ValueError(f"kind must be 'keypoints' or 'surface', got {kind!r}")
    rng = np.random.default_rng(seed)
    areas = np.array([d[1] * d[2], d[0] * d[2], d[0] * d[1]])  # faces normal to x, y, z
    axis = rng.choice(3, size=n, p=areas / areas.sum())
    pts = (rng.random((n, 3)) - 0.5) * d
    side = np.where(rng.random(n) < 0.5, -0.5, 0.5)
    pts[np.arange(n), axis] = side * d[axis]
    return pts


def add_error(T_est: np.ndarray, T_gt: np.ndarray, model_points: np.ndarray) -> float:
    """ADD: mean distance between model points under the estimated and the true pose (metres)."""
    a = model_points @ T_est[:3, :3].T + T_est[:3, 3]
    b = model_points @ T_gt[:3, :3].T + T_gt[:3, 3]
    return float(np.mean(np.linalg.norm(a - b, axis=1)))


def adds_error(T_est: np.ndarray, T_gt: np.ndarray, model_points: np.ndarray) -> float:
    """ADD-S: mean over estimated points of the distance to the closest true point (symmetric objects)."""
    from scipy.spatial import cKDTree

    a = model_points @ T_est[:3, :3].T + T_est[:3, 3]
    b = model_points @ T_gt[:3, :3].T + T_gt[:3, 3]
    dist, _ = cKDTree(b).query(a)
    return float(np.mean(dist))


# --------------------------------------------------------------------------------------------
# the paper's equations (positions in the camera optical frame: x right, z forward)


def paper_distance_xz(truth_xyz, detected_xyz) -> float:
    """Eq. 6: sqrt(dx^2 + dz^2) between true and detected positions (the grid experiment ignores y)."""
    t, d = np.asarray(truth_xyz, dtype=float), np.asarray(detected_xyz, dtype=float)
    return float(np.hypot(t[0] - d[0], t[2] - d[2]))


def paper_accuracy(truth_xyz, detected_xyz) -> float:
    """Eq. 7: 1 - | |T| - |D| | / |T| with |.| the x-z distance from the camera origin."""
    t, d = np.asarray(truth_xyz, dtype=float), np.asarray(detected_xyz, dtype=float)
    rt, rd = np.hypot(t[0], t[2]), np.hypot(d[0], d[2])
    if rt == 0:
        raise ValueError("eq. 7 is undefined for a ground truth at the camera origin")
    return float(1.0 - abs((rt - rd) / rt))


def paper_label_distance(truth_xyz, detected_xyz) -> float:
    """Eq. 8 (with the '+' the typeset formula drops): Euclidean distance of a map label to the truth."""
    return float(np.linalg.norm(np.asarray(truth_xyz, dtype=float) - np.asarray(detected_xyz, dtype=float)))


def is_false_positive(truth_xyz, detected_xyz, tol_m: float = 0.05) -> bool:
    """The paper's false positive: more than ``tol_m`` (5 cm) from the truth in any axis."""
    delta = np.abs(np.asarray(truth_xyz, dtype=float) - np.asarray(detected_xyz, dtype=float))
    return bool(np.any(delta > tol_m))


@dataclass
class PrecisionRecall:
    precision: float
    recall: float
    f_score: float
    correct: int  # CP = TP - FP


def precision_recall_f(total_predictions: int, false_positives: int, total_instances: int) -> PrecisionRecall:
    """Eq. 3-5 with the paper's names: TP = all predictions, FP = false ones, TI = instances present.

    CP = TP - FP; precision = CP / TP; recall = CP / TI; F = 2 CP / (TP + TI). A ratio with a zero
    denominator is NaN.
    """
    tp, fp, ti = int(total_predictions), int(false_positives), int(total_instances)
    if min(tp, fp, ti) < 0 or fp > tp:
        raise ValueError(f"expected 0 <= FP <= TP and TI >= 0, got TP={tp} FP={fp} TI={ti}")
    cp = tp - fp
    nan = float("nan")
    return PrecisionRecall(cp / tp if tp else nan, cp / ti if ti else nan,
                           2 * cp / (tp + ti) if tp + ti else nan, cp)
