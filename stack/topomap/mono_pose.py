"""Monocular camera pose from an image sequence (the topological-map paper, section 2.2): ORPE and two baselines.

The pipeline (the paper's steps 1-7):

1. Initialise with the first two key frames and the distance between them (the "given baseline"):
   essential matrix in RANSAC (OpenCV), decomposition, cheirality; triangulated points fix the
   world frame (= the first key frame's camera) and the metric scale.
2. Every new frame: Shi-Tomasi corners on the Gaussian-blurred image, upright SIFT descriptors
   (L2-normalised), matched to the last key frame inside a search region (0.08 x max(width,
   height)), descriptor distance below 0.4, one-to-one. Frames matching below 20 % are discarded.
3. Pose from the matches whose 3D point is known, by one of three estimators:
   - ``orpe`` (the paper's method): ONE RANSAC. Each hypothesis: eight sampled matches -> essential
     matrix (our own eight-point) -> its four (R, t-direction) decompositions; the translation's
     length from each of four sampled points with known 3D (collinearity of the bearing with
     ``R X + s t``), i.e. 16 translation distances; the hypothesis with the most reprojection
     inliers (< 2 px) wins. Adaptive stopping at 99 % confidence. (For speed each batch of
     hypotheses is first scored on 24 random points and only the best four on all of them.)
   - ``trpe`` (Wu's two-RANSAC method, the paper's foil): RANSAC 1 finds the best essential matrix
     from all 2D-2D matches (OpenCV's ``findEssentialMat``, Sampson error, MSAC), its (R, t-direction)
     chosen by cheirality (``recoverPose``); RANSAC 2
     then finds the translation's length from single 3D points. When the essential matrix is
     degenerate (small baseline, near-planar structure) RANSAC 2 has nothing right to scale.
   - ``grunert`` (the classical P3P): Grunert's solution (as reviewed by Haralick et al. 1994) in a
     RANSAC over three map points, up to four poses each.
4. Levenberg-Marquardt refinement of the pose on the inliers (reprojection error < 2 px; OpenCV's
   ``solvePnPRefineLM``).
5. Key frames: a frame becomes one when enough image motion has built up; new points are
   triangulated between it and the previous key frame (negative, very far and low-parallax points
   dropped).
6. Local bundle adjustment over the last six key frames, only the last two poses (and the points
   they see) optimised (scipy ``least_squares``, sparse Jacobian, Huber loss).

Steps 1 and 5-7 (initialisation, key frames, local bundle adjustment, the sequence) are
``stack.topomap.mono_vo``; this module holds the features, matching, geometry and the estimators.

Poses: ``T_cw`` maps world points into the camera (x_c = R X_w + t); ``T_world_camera`` is its
inverse. World = the first key frame's camera optical frame, scaled by the given baseline.

One deviation from the seed, said here: the search region is centred where a pure rotation at the
last frame-to-frame rotation rate would move the feature (the KITTI car turned ~2 deg per frame,
the Jackal turns up to 8 deg per 10-Hz frame, which would leave the paper's region).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)
METHODS = ("orpe", "trpe", "grunert")


@dataclass
class MonoConfig:
    max_corners: int = 800
    corner_quality: float = 0.002
    corner_min_distance: int = 6
    blur_sigma: float = 1.0
    min_eigenvalue: float = 2e-5  # absolute corner strength (image scaled to 0..1, 5x5 window)
    sift_size: float = 8.0  # SIFT key-point size (pixels): the descriptor spans about 6 x this
    search_radius_frac: float = 0.08  # of max(width, height)
    max_descriptor_distance: float = 0.4  # L2 between L2-normalised SIFT descriptors
    min_match_ratio: float = 0.2  # matched / detected in the key frame; below it the frame is discarded
    inlier_px: float = 2.0
    # Sampson distance (pixels) for an inlier of TRPE's essential matrix (the initialisation's keeps
    # inlier_px). OpenCV's five-point RANSAC at 2 px let TRPE fail in 12 of 30 seeded runs on
    # experiment3_columns and 20 of 30 on shelf_corridor; at 1 px, 2 and 5 (docs/topological_map.md).
    trpe_essential_px: float = 1.0
    confidence: float = 0.99
    max_iterations: int = 1000
    min_iterations: int = 20
    min_inliers: int = 15
    keyframe_every: int = 10  # frames; a key frame is also made earlier when overlap or motion demand it
    keyframe_min_flow_frac: float = 0.005  # of max(width, height): no key frame while the image has not moved
    keyframe_max_flow_frac: float = 0.04  # of max(width, height): make a key frame beyond this median motion
    keyframe_min_overlap: float = 0.45  # make a key frame when fewer of the key frame's features match
    min_parallax_deg: float = 1.0  # triangulated points need this much viewing-angle difference
    max_depth_m: float = 30.0
    ba: bool = True
    ba_window: int = 6
    ba_optimise: int = 2
    ba_max_nfev: int = 15
    fail_streak: int = 5  # the seed: five connected frames failing = the SLAM fails


# --- features and matching -------------------------------------------------------------------------

@dataclass
class Features:
    uv: np.ndarray  # (N, 2) float64 pixels
    desc: np.ndarray  # (N, 128) float32, L2-normalised

    def __len__(self) -> int:
        return len(self.uv)


_SIFT = None


def detect_features(gray: np.ndarray, cfg: MonoConfig = MonoConfig()) -> Features:
    """Shi-Tomasi corners (sub-pixel) on the blurred image, described by upright SIFT."""
    global _SIFT
    if _SIFT is None:
        _SIFT = cv2.SIFT_create()
    img = cv2.GaussianBlur(gray, (0, 0), cfg.blur_sigma) if cfg.blur_sigma > 0 else gray
    pts = cv2.goodFeaturesToTrack(img, cfg.max_corners, cfg.corner_quality, cfg.corner_min_distance, blockSize=5)
    if pts is None or len(pts) == 0:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    if cfg.min_eigenvalue > 0:  # an absolute floor, so that sensor noise on bare walls gives no corners
        eig = cv2.cornerMinEigenVal(img.astype(np.float32) / 255.0, 5)
        xi = np.clip(np.rint(pts[:, 0, 0]).astype(int), 0, img.shape[1] - 1)
        yi = np.clip(np.rint(pts[:, 0, 1]).astype(int), 0, img.shape[0] - 1)
        pts = pts[eig[yi, xi] >= cfg.min_eigenvalue]
        if len(pts) == 0:
            return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    pts = cv2.cornerSubPix(img, pts.astype(np.float32), (3, 3), (-1, -1),
                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.03))
    kps = [cv2.KeyPoint(float(x), float(y), cfg.sift_size, 0.0) for x, y in pts.reshape(-1, 2)]
    kps, desc = _SIFT.compute(img, kps)
    if desc is None or len(kps) == 0:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    uv = np.array([k.pt for k in kps], dtype=np.float64)
    desc = desc.astype(np.float32)
    desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-9)
    return Features(uv, desc)


def match_features(kf: Features, cur: Features, radius_px: float, max_dist: float,
                   predicted_uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every key-frame feature, the nearest descriptor among current features inside the search
    region (around ``predicted_uv`` when given); distance below ``max_dist``; one-to-one.
    Returns (index in kf, index in cur, descriptor distance)."""
    if len(kf) == 0 or len(cur) == 0:
        e = np.zeros(0, dtype=int)
        return e, e, np.zeros(0)
    centres = kf.uv if predicted_uv is None else predicted_uv
    tree = cKDTree(cur.uv)
    lists = tree.query_ball_point(centres, radius_px)
    lens = np.fromiter((len(c) for c in lists), dtype=int, count=len(lists))
    if lens.sum() == 0:
        e = np.zeros(0, dtype=int)
        return e, e, np.zeros(0)
    ii = np.repeat(np.arange(len(kf)), lens)
    jj = np.fromiter((j for c in lists for j in c), dtype=int, count=int(lens.sum()))
    d = np.sqrt(np.maximum(2.0 - 2.0 * np.einsum("ij,ij->i", kf.desc[ii], cur.desc[jj]), 0.0))
    ok = d < max_dist
    ii, jj, d = ii[ok], jj[ok], d[ok]
    if len(ii) == 0:
        return ii, jj, d
    # best per key-frame feature, then best per current feature (one correspondence each)
    order = np.lexsort((d, ii))
    ii, jj, d = ii[order], jj[order], d[order]
    first = np.r_[True, ii[1:] != ii[:-1]]
    ii, jj, d = ii[first], jj[first], d[first]
    order = np.lexsort((d, jj))
    ii, jj, d = ii[order], jj[order], d[order]
    first = np.r_[True, jj[1:] != jj[:-1]]
    return ii[first], jj[first], d[first]


# --- geometry ------------------------------------------------------------------------------------

def normalise(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels -> normalised image coordinates (N, 2)."""
    return np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]])


def bearings(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    x = np.column_stack([normalise(uv, K), np.ones(len(uv))])
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and depths of world points X (N, 3) in camera (R, t); broadcasts over leading dims of R, t."""
    Xc = np.einsum("...ij,nj->...ni", R, X) + t[..., None, :]
    z = Xc[..., 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = K[0, 0] * Xc[..., 0] / zs + K[0, 2]
    v = K[1, 1] * Xc[..., 1] / zs + K[1, 2]
    return np.stack([u, v], axis=-1), z


def reprojection_errors(K, R, t, X, uv) -> np.ndarray:
    """Pixel errors (inf behind the camera); broadcasts over leading dims of R, t."""
    px, z = project(K, R, t, X)
    err = np.linalg.norm(px - uv, axis=-1)
    return np.where(z > 1e-6, err, np.inf)


def _hartley(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched normalising similarity for (B, n, 2) points: returns normalised (B, n, 3) and T (B, 3, 3)."""
    c = x.mean(axis=1, keepdims=True)
    d = np.sqrt(((x - c) ** 2).sum(-1)).mean(axis=1)
    s = np.sqrt(2.0) / np.maximum(d, 1e-12)
    B = x.shape[0]
    T = np.zeros((B, 3, 3))
    T[:, 0, 0] = s
    T[:, 1, 1] = s
    T[:, 0, 2] = -s * c[:, 0, 0]
    T[:, 1, 2] = -s * c[:, 0, 1]
    T[:, 2, 2] = 1.0
    xn = np.concatenate([(x - c) * s[:, None, None], np.ones(x.shape[:2] + (1,))], axis=-1)
    return xn, T


def eight_point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Essential matrices from >= 8 correspondences of normalised coordinates, batched:
    x1, x2 (B, n, 2) or (n, 2) with x2^T E x1 = 0. Hartley normalisation, then the (1, 1, 0) projection."""
    single = x1.ndim == 2
    if single:
        x1, x2 = x1[None], x2[None]
    p1, T1 = _hartley(x1)
    p2, T2 = _hartley(x2)
    A = (p2[..., :, None] * p1[..., None, :]).reshape(x1.shape[0], x1.shape[1], 9)
    _, _, Vt = np.linalg.svd(A)
    F = Vt[:, -1].reshape(-1, 3, 3)
    E = np.transpose(T2, (0, 2, 1)) @ F @ T1
    U, _, Vt = np.linalg.svd(E)
    E = U @ np.diag([1.0, 1.0, 0.0]) @ Vt
    E /= np.linalg.norm(E, axis=(1, 2), keepdims=True)
    return E[0] if single else E


_W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def decompose_essential(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The four (R, t-direction) of essential matrices (B, 3, 3) -> R (B, 4, 3, 3), t (B, 4, 3) with
    x2 ~ R x1 + t."""
    single = E.ndim == 2
    if single:
        E = E[None]
    U, _, Vt = np.linalg.svd(E)
    U = U * np.where(np.linalg.det(U) < 0, -1.0, 1.0)[:, None, None]
    Vt = Vt * np.where(np.linalg.det(Vt) < 0, -1.0, 1.0)[:, None, None]
    Ra = U @ _W @ Vt
    Rb = U @ _W.T @ Vt
    t = U[:, :, 2]
    R = np.stack([Ra, Ra, Rb, Rb], axis=1)
    T = np.stack([t, -t, t, -t], axis=1)
    return (R[0], T[0]) if single else (R, T)


def scale_from_point(R: np.ndarray, t_dir: np.ndarray, X: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """The translation's length s so that the bearing x2 (homogeneous, ..., 3) is collinear with
    R X + s t_dir (least squares of the cross product), broadcasting."""
    a = np.cross(x2, np.einsum("...ij,...j->...i", R, X))
    b = np.cross(x2, t_dir)
    return -np.einsum("...i,...i->...", a, b) / np.maximum(np.einsum("...i,...i->...", b, b), 1e-18)


def triangulate(K: np.ndarray, T1_cw: np.ndarray, T2_cw: np.ndarray, uv1: np.ndarray, uv2: np.ndarray,
                min_parallax_deg: float = 1.0, max_depth: float = 30.0, max_err_px: float = 2.0):
    """Linear (DLT) triangulation of matched pixels; returns world points (N, 3) and the valid mask
    (in front of both cameras, not too far, enough parallax, reprojecting within ``max_err_px``)."""
    if len(uv1) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    P1 = K @ T1_cw[:3]
    P2 = K @ T2_cw[:3]
    Xh = cv2.triangulatePoints(P1, P2, uv1.T.astype(np.float64), uv2.T.astype(np.float64))
    w = Xh[3]
    ok = np.abs(w) > 1e-12
    X = (Xh[:3] / np.where(ok, w, 1.0)).T
    e1 = reprojection_errors(K, T1_cw[:3, :3], T1_cw[:3, 3], X, uv1)
    e2 = reprojection_errors(K, T2_cw[:3, :3], T2_cw[:3, 3], X, uv2)
    z1 = X @ T1_cw[2, :3] + T1_cw[2, 3]
    z2 = X @ T2_cw[2, :3] + T2_cw[2, 3]
    c1 = -T1_cw[:3, :3].T @ T1_cw[:3, 3]
    c2 = -T2_cw[:3, :3].T @ T2_cw[:3, 3]
    r1 = X - c1
    r2 = X - c2
    cosang = np.einsum("ij,ij->i", r1, r2) / np.maximum(np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1), 1e-12)
    parallax = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    ok &= (z1 > 0.05) & (z2 > 0.05) & (z1 < max_depth) & (z2 < max_depth)
    ok &= (e1 < max_err_px) & (e2 < max_err_px) & (parallax >= min_parallax_deg)
    return X, ok


def _rt_to_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _rotvec(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.ascontiguousarray(R))[0].ravel()


def _rotmat(r: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(r, dtype=np.float64).reshape(3, 1))[0]


def refine_pose_lm(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, uv: np.ndarray,
                   iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the reprojection error of (R, t) over the given 3D-2D inliers
    (OpenCV's ``solvePnPRefineLM``)."""
    if len(X) < 4:
        return R, t
    rvec = _rotvec(R).reshape(3, 1).astype(np.float64)
    tvec = np.asarray(t, dtype=np.float64).reshape(3, 1).copy()
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, iterations, 1e-10)
    rvec, tvec = cv2.solvePnPRefineLM(np.ascontiguousarray(X, dtype=np.float64),
                                      np.ascontiguousarray(uv, dtype=np.float64), K.astype(np.float64), None,
                                      rvec, tvec, criteria)
    if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return R, t
    return _rotmat(rvec), tvec.ravel().copy()


def _samples(rng: np.random.Generator, n: int, k: int, batch: int) -> np.ndarray:
    """``batch`` random subsets of ``k`` distinct indices out of ``n``."""
    return np.argpartition(rng.random((batch, n)), k - 1, axis=1)[:, :k]


def _needed_iterations(inlier_ratio: float, sample: int, confidence: float, cap: int) -> int:
    w = min(max(inlier_ratio, 1e-6), 1.0 - 1e-12)
    denom = math.log(max(1e-300, 1.0 - w ** sample))
    if denom >= 0:
        return cap
    return int(min(cap, math.ceil(math.log(1.0 - confidence) / denom)))


# --- the three estimators ---------------------------------------------------------------------------

@dataclass
class PoseEstimate:
    R: np.ndarray  # current camera from key-frame camera: x_cur = R x_kf + t
    t: np.ndarray
    inliers: np.ndarray  # bool over the 3D-2D correspondences given
    iterations: int
    ransac_inliers: int = 0  # support of the RANSAC hypothesis before the LM refinement


def orpe(K: np.ndarray, X_kf: np.ndarray, uv_kf: np.ndarray, uv_cur: np.ndarray, rng: np.random.Generator,
         cfg: MonoConfig = MonoConfig(), batch: int = 32, preview: int = 24, finalists: int = 4) -> PoseEstimate | None:
    """One-point RANSAC pose (ORPE) of the current camera relative to the key frame.

    X_kf: (N, 3) known points in the key frame's camera; uv_kf, uv_cur: their pixels in both images."""
    n = len(X_kf)
    if n < 8:
        return None
    x1 = normalise(uv_kf, K)
    x2 = normalise(uv_cur, K)
    x2h = np.column_stack([x2, np.ones(n)])
    fx, fy = K[0, 0], K[1, 1]
    u0, v0 = uv_cur[:, 0] - K[0, 2], uv_cur[:, 1] - K[1, 2]
    thr2 = cfg.inlier_px ** 2
    best_count, best = -1, None
    needed, done = cfg.max_iterations, 0
    while done < min(needed, cfg.max_iterations) or done < cfg.min_iterations:
        B = batch
        idx = _samples(rng, n, 8, B)
        E = eight_point(x1[idx], x2[idx])
        R, tdir = decompose_essential(E)  # (B, 4, 3, 3), (B, 4, 3)
        # the translation's length from each of four sampled points: 16 candidate translations
        pts = idx[:, :4]
        s = scale_from_point(R[:, :, None], tdir[:, :, None], X_kf[pts][:, None], x2h[pts][:, None])  # (B, 4, 4)
        t = s[..., None] * tdir[:, :, None, :]  # (B, 4, 4, 3)
        # pre-emptive scoring (it keeps RANSAC's result, not its cost): all 16 B hypotheses on a
        # random subset of the points, then the most promising few on all of them
        sub = rng.choice(n, preview, replace=False) if n > preview else np.arange(n)
        RX = np.matmul(X_kf[sub][None, None], np.swapaxes(R, -1, -2))  # (B, 4, m, 3), shared by the 4 lengths
        Xc = RX[:, :, None] + t[:, :, :, None, :]  # (B, 4, 4, m, 3)
        z = Xc[..., 2]
        zs = np.where(z > 1e-6, z, 1e-6)
        du = fx * Xc[..., 0] / zs - u0[sub]
        dv = fy * Xc[..., 1] / zs - v0[sub]
        sub_counts = (((du * du + dv * dv) < thr2) & (z > 1e-6)).sum(-1)
        done += B
        for flat in np.argsort(sub_counts.ravel(), kind="stable")[-finalists:]:
            b, i, j = np.unravel_index(int(flat), sub_counts.shape)
            c = int((reprojection_errors(K, R[b, i], t[b, i, j], X_kf, uv_cur) < cfg.inlier_px).sum())
            if c > best_count:
                best_count = c
                best = (R[b, i].copy(), t[b, i, j].copy())
                needed = _needed_iterations(best_count / n, 8, cfg.confidence, cfg.max_iterations)
    return _finish(K, best, X_kf, uv_cur, done, cfg)


def _finish(K, best, X, uv, iterations, cfg) -> PoseEstimate | None:
    """LM refinement on the inliers, then the inliers again; None when too few support the pose."""
    if best is None:
        return None
    R, t = best
    inl = reprojection_errors(K, R, t, X, uv) < cfg.inlier_px
    n_ransac = int(inl.sum())
    if n_ransac < cfg.min_inliers:
        return None
    for _ in range(2):
        R, t = refine_pose_lm(K, R, t, X[inl], uv[inl])
        new = reprojection_errors(K, R, t, X, uv) < cfg.inlier_px
        if new.sum() < cfg.min_inliers:
            return None
        if np.array_equal(new, inl):
            break
        inl = new
    return PoseEstimate(R, t, inl, iterations, n_ransac)


def essential_ransac(K: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, rng: np.random.Generator,
                     cfg: MonoConfig = MonoConfig(), threshold_px: float | None = None):
    """Best essential matrix in RANSAC (OpenCV's ``findEssentialMat``: five-point hypotheses, MSAC score
    on the Sampson error with threshold ``threshold_px`` (default ``cfg.inlier_px``), local optimisation
    and a least-squares polish on the inliers, seeded from ``rng``); returns (E, inlier mask) or None."""
    if len(uv1) < 8:
        return None
    p = cv2.UsacParams()
    p.confidence, p.maxIterations = cfg.confidence, cfg.max_iterations
    p.threshold = cfg.inlier_px if threshold_px is None else threshold_px
    p.randomGeneratorState = int(rng.integers(2**31 - 1))
    p.sampler, p.score = cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_MSAC
    p.loMethod, p.loIterations, p.loSampleSize = cv2.LOCAL_OPTIM_GC, 10, 14
    p.final_polisher, p.final_polisher_iterations = cv2.LSQ_POLISHER, 3
    K = K.astype(np.float64)
    try:
        E, mask = cv2.findEssentialMat(np.ascontiguousarray(uv1, dtype=np.float64),
                                       np.ascontiguousarray(uv2, dtype=np.float64), K, K, None, None, p)
    except cv2.error:  # a degenerate configuration
        return None
    if E is None or E.shape[0] < 3 or mask is None or int(mask.sum()) < 8:
        return None
    return E[:3].copy(), mask.ravel().astype(bool)


RECOVER_POSE_MAX_DEPTH = 1e9  # in baselines: no cut


def pose_from_essential(K: np.ndarray, E: np.ndarray, uv1: np.ndarray, uv2: np.ndarray):
    """The decomposition of E that puts most points in front of both cameras (OpenCV's ``recoverPose``):
    (R, unit t, the number of points in front). No distance cut: OpenCV's default drops points farther
    than 50 baselines, which between near frames (a few centimetres apart) is every point, and the
    choice among the four decompositions becomes arbitrary."""
    n, R, t, _, _ = cv2.recoverPose(E, np.ascontiguousarray(uv1, dtype=np.float64),
                                    np.ascontiguousarray(uv2, dtype=np.float64), K.astype(np.float64),
                                    distanceThresh=RECOVER_POSE_MAX_DEPTH)
    return R, t.ravel() / max(float(np.linalg.norm(t)), 1e-12), int(n)


def trpe(K: np.ndarray, X_kf: np.ndarray, uv_kf3: np.ndarray, uv_cur3: np.ndarray, uv_kf_all: np.ndarray,
         uv_cur_all: np.ndarray, rng: np.random.Generator, cfg: MonoConfig = MonoConfig()) -> PoseEstimate | None:
    """Two-RANSAC pose (TRPE, Wu et al.): essential matrix from all 2D-2D matches, then the translation
    length from single 3D points."""
    res = essential_ransac(K, uv_kf_all, uv_cur_all, rng, cfg, cfg.trpe_essential_px)
    if res is None or len(X_kf) < 1:
        return None
    E, inl_e = res
    R, tdir, _ = pose_from_essential(K, E, uv_kf_all[inl_e], uv_cur_all[inl_e])
    x2h = np.column_stack([normalise(uv_cur3, K), np.ones(len(uv_cur3))])
    s_all = scale_from_point(R, tdir, X_kf, x2h)  # one hypothesis per 3D point
    n = len(X_kf)
    best_count, best = -1, None
    needed, done = cfg.max_iterations, 0
    order = rng.permutation(n)
    while done < min(needed, n) or (done < min(cfg.min_iterations, n)):
        j = order[done]
        t = s_all[j] * tdir
        c = int((reprojection_errors(K, R, t, X_kf, uv_cur3) < cfg.inlier_px).sum())
        done += 1
        if c > best_count:
            best_count, best = c, (R, t)
            needed = _needed_iterations(best_count / n, 1, cfg.confidence, cfg.max_iterations)
    return _finish(K, best, X_kf, uv_cur3, done, cfg)


def grunert_p3p(bearing: np.ndarray, X: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Grunert's three-point pose (Haralick et al. 1994, section 2): unit bearings (3, 3) of three
    world points X (3, 3) -> up to four (R, t) with bearing_i ~ R X_i + t."""
    p1, p2, p3 = X
    j1, j2, j3 = bearing
    a2 = float(np.sum((p2 - p3) ** 2))
    b2 = float(np.sum((p1 - p3) ** 2))
    c2 = float(np.sum((p1 - p2) ** 2))
    if min(a2, b2, c2) < 1e-16:
        return []
    ca, cb, cg = float(j2 @ j3), float(j1 @ j3), float(j1 @ j2)
    amc = (a2 - c2) / b2
    apc = (a2 + c2) / b2
    A4 = (amc - 1) ** 2 - 4 * c2 / b2 * ca ** 2
    A3 = 4 * (amc * (1 - amc) * cb - (1 - apc) * ca * cg + 2 * c2 / b2 * ca ** 2 * cb)
    A2 = 2 * (amc ** 2 - 1 + 2 * amc ** 2 * cb ** 2 + 2 * (b2 - c2) / b2 * ca ** 2
              - 4 * apc * ca * cb * cg + 2 * (b2 - a2) / b2 * cg ** 2)
    A1 = 4 * (-amc * (1 + amc) * cb + 2 * a2 / b2 * cg ** 2 * cb - (1 - apc) * ca * cg)
    A0 = (1 + amc) ** 2 - 4 * a2 / b2 * cg ** 2
    roots = np.roots([A4, A3, A2, A1, A0])
    out = []
    for v in roots:
        if abs(v.imag) > 1e-6 * max(1.0, abs(v.real)):
            continue
        v = float(v.real)
        den = 2 * (cg - v * ca)
        if abs(den) < 1e-12:
            continue
        u = ((-1 + amc) * v * v - 2 * amc * cb * v + 1 + amc) / den
        q = 1 + u * u - 2 * u * cg
        if q <= 1e-12:
            continue
        s1 = math.sqrt(c2 / q)
        s2, s3 = u * s1, v * s1
        if s1 <= 0 or s2 <= 0 or s3 <= 0:
            continue
        P = np.stack([s1 * j1, s2 * j2, s3 * j3])
        out.append(_absolute_orientation(X, P))
    return out


def _absolute_orientation(X: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation with P_i = R X_i + t (least squares, Kabsch/Umeyama without scale)."""
    mx, mp = X.mean(0), P.mean(0)
    H = (X - mx).T @ (P - mp)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mp - R @ mx


def grunert(K: np.ndarray, X_kf: np.ndarray, uv_cur: np.ndarray, rng: np.random.Generator,
            cfg: MonoConfig = MonoConfig()) -> PoseEstimate | None:
    """Grunert's P3P in RANSAC over the known points, then the same LM refinement."""
    n = len(X_kf)
    if n < 4:
        return None
    bear = bearings(uv_cur, K)
    best_count, best = -1, None
    needed, done = cfg.max_iterations, 0
    while done < min(needed, cfg.max_iterations) or done < cfg.min_iterations:
        idx = rng.choice(n, 3, replace=False)
        done += 1
        for R, t in grunert_p3p(bear[idx], X_kf[idx]):
            c = int((reprojection_errors(K, R, t, X_kf, uv_cur) < cfg.inlier_px).sum())
            if c > best_count:
                best_count, best = c, (R, t)
                needed = _needed_iterations(best_count / n, 3, cfg.confidence, cfg.max_iterations)
    return _finish(K, best, X_kf, uv_cur, done, cfg)
