"""Monocular visual odometry and mapping over an image sequence (the topological-map paper, section 2.2,
steps 1-7): ``MonoVO`` initialises from two key frames and a given baseline, tracks every frame with
one of the pose estimators of ``stack.topomap.mono_pose`` (ORPE, TRPE, Grunert's P3P), makes key
frames and triangulates new points; ``local_bundle_adjustment`` optimises the last key frames (scipy
``least_squares``, sparse Jacobian, Huber loss); ``run_sequence`` runs it over a whole sequence.

Poses: ``T_cw`` maps world points into the camera (x_c = R X_w + t). World = the first key frame's
camera optical frame, scaled by the given baseline.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from stack.topomap.mono_pose import (Features, METHODS, MonoConfig, _rotmat, _rotvec, _rt_to_T,
                                     detect_features, essential_ransac, grunert, match_features, orpe,
                                     pose_from_essential, triangulate, trpe)

log = logging.getLogger(__name__)

@dataclass
class KeyFrame:
    index: int  # frame index in the sequence
    stamp: float
    feats: Features
    pid: np.ndarray  # (N,) map point id per feature, -1 none
    T_cw: np.ndarray  # 4x4 world -> camera
    origin_kf: np.ndarray | None = None  # (N,) for a feature tracked without a point: the key frame ...
    origin_feat: np.ndarray | None = None  # ... and feature where its track began (-1: here)

    def __post_init__(self):
        if self.origin_kf is None:
            self.origin_kf = np.full(len(self.feats), -1)
            self.origin_feat = np.full(len(self.feats), -1)


@dataclass
class FrameResult:
    index: int
    stamp: float
    ok: bool
    T_world_camera: np.ndarray | None
    keyframe: bool
    matches: int
    known: int  # matches with a known 3D point
    inliers: int
    seconds: float
    reason: str = ""


@dataclass
class MonoVO:
    """Monocular visual odometry with one of the three pose estimators; feed frames in order."""

    K: np.ndarray
    image_size: tuple[int, int]  # width, height
    method: str = "orpe"
    cfg: MonoConfig = field(default_factory=MonoConfig)
    seed: int = 0

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {self.method!r}")
        self.rng = np.random.default_rng(self.seed)
        self.keyframes: list[KeyFrame] = []
        self.points: list[np.ndarray] = []
        self.results: list[FrameResult] = []
        self.fail_streak = 0
        self.failed = False
        self._last_T_cw: np.ndarray | None = None
        self._prev_T_cw: np.ndarray | None = None
        self._since_kf = 0
        self.ba_seconds = 0.0

    # -- helpers
    @property
    def radius(self) -> float:
        return self.cfg.search_radius_frac * max(self.image_size)

    def _add_points(self, X: np.ndarray) -> np.ndarray:
        start = len(self.points)
        self.points.extend(np.asarray(X, dtype=float))
        return np.arange(start, start + len(X))

    def point_array(self) -> np.ndarray:
        return np.asarray(self.points).reshape(-1, 3)

    def _predict(self, kf: KeyFrame) -> np.ndarray | None:
        """Where the key frame's features would be after the rotation predicted at a constant rate."""
        if self._last_T_cw is None or self._prev_T_cw is None:
            return None
        R_step = self._last_T_cw[:3, :3] @ self._prev_T_cw[:3, :3].T
        R_pred = R_step @ self._last_T_cw[:3, :3]
        R_rel = R_pred @ kf.T_cw[:3, :3].T
        H = self.K @ R_rel @ np.linalg.inv(self.K)
        uvh = np.column_stack([kf.feats.uv, np.ones(len(kf.feats))]) @ H.T
        return uvh[:, :2] / uvh[:, 2:3]

    # -- initialisation
    def initialise(self, feats0: Features, feats1: Features, baseline_m: float, index0: int = 0, index1: int = 1,
                   stamp0: float = 0.0, stamp1: float = 0.0) -> bool:
        """World frame and scale from the first two key frames and the distance between them."""
        i0, i1, _ = match_features(feats0, feats1, self.radius * 2, self.cfg.max_descriptor_distance)
        if len(i0) < 20:
            return False
        res = essential_ransac(self.K, feats0.uv[i0], feats1.uv[i1], self.rng, self.cfg)
        if res is None:
            return False
        E, inl = res
        R, tdir, _ = pose_from_essential(self.K, E, feats0.uv[i0][inl], feats1.uv[i1][inl])
        T0 = np.eye(4)
        T1 = _rt_to_T(R, tdir / np.linalg.norm(tdir) * baseline_m)
        X, ok = triangulate(self.K, T0, T1, feats0.uv[i0][inl], feats1.uv[i1][inl], self.cfg.min_parallax_deg,
                            self.cfg.max_depth_m, self.cfg.inlier_px)
        if ok.sum() < 20:
            return False
        pid0 = np.full(len(feats0), -1)
        pid1 = np.full(len(feats1), -1)
        ids = self._add_points(X[ok])
        a, b = i0[inl][ok], i1[inl][ok]
        pid0[a] = ids
        pid1[b] = ids
        self.keyframes = [KeyFrame(index0, stamp0, feats0, pid0, T0), KeyFrame(index1, stamp1, feats1, pid1, T1)]
        self._prev_T_cw, self._last_T_cw = T0, T1
        self._since_kf = 0
        return True

    # -- one frame
    def process(self, feats: Features, index: int, stamp: float, feature_seconds: float = 0.0) -> FrameResult:
        t0 = time.perf_counter()
        kf = self.keyframes[-1]
        cfg = self.cfg
        ik, ic, _ = match_features(kf.feats, feats, self.radius, cfg.max_descriptor_distance, self._predict(kf))
        ratio = len(ik) / max(1, len(kf.feats))
        if ratio < cfg.min_match_ratio:
            return self._fail(index, stamp, len(ik), 0, t0, feature_seconds, "too few matches")
        known = kf.pid[ik] >= 0
        P = self.point_array()
        Xw = P[kf.pid[ik[known]]]
        X_kf = Xw @ kf.T_cw[:3, :3].T + kf.T_cw[:3, 3]
        uv_kf3, uv_cur3 = kf.feats.uv[ik[known]], feats.uv[ic[known]]
        if self.method == "orpe":
            est = orpe(self.K, X_kf, uv_kf3, uv_cur3, self.rng, cfg)
        elif self.method == "trpe":
            est = trpe(self.K, X_kf, uv_kf3, uv_cur3, kf.feats.uv[ik], feats.uv[ic], self.rng, cfg)
        else:
            est = grunert(self.K, X_kf, uv_cur3, self.rng, cfg)
        if est is None:
            return self._fail(index, stamp, len(ik), int(known.sum()), t0, feature_seconds, "no pose")
        T_cw = _rt_to_T(est.R, est.t) @ kf.T_cw
        self.fail_streak = 0
        self._prev_T_cw, self._last_T_cw = self._last_T_cw, T_cw
        self._since_kf += 1
        # key-frame decision: enough image motion, or the overlap with the key frame running out
        flow = float(np.median(np.linalg.norm(feats.uv[ic] - kf.feats.uv[ik], axis=1)))
        make_kf = flow >= cfg.keyframe_min_flow_frac * max(self.image_size) and (
            self._since_kf >= cfg.keyframe_every or ratio < cfg.keyframe_min_overlap
            or flow > cfg.keyframe_max_flow_frac * max(self.image_size))
        if make_kf:
            self._new_keyframe(kf, feats, ik, ic, known, est.inliers, T_cw, index, stamp)
            T_cw = self.keyframes[-1].T_cw  # after bundle adjustment
            self._last_T_cw = T_cw
        res = FrameResult(index, stamp, True, np.linalg.inv(T_cw), make_kf, len(ik), int(known.sum()),
                          int(est.inliers.sum()), time.perf_counter() - t0 + feature_seconds)
        self.results.append(res)
        return res

    def _fail(self, index, stamp, matches, known, t0, feature_seconds, reason) -> FrameResult:
        self.fail_streak += 1
        if self.fail_streak >= self.cfg.fail_streak:
            self.failed = True
        res = FrameResult(index, stamp, False, None, False, matches, known, 0,
                          time.perf_counter() - t0 + feature_seconds, reason)
        self.results.append(res)
        return res

    def _new_keyframe(self, kf: KeyFrame, feats: Features, ik, ic, known, inliers, T_cw, index, stamp) -> None:
        pid = np.full(len(feats), -1)
        origin_kf = np.full(len(feats), -1)
        origin_feat = np.full(len(feats), -1)
        kin = np.flatnonzero(known)
        good = kin[inliers]
        pid[ic[good]] = kf.pid[ik[good]]
        # matches without a point: triangulate from where their track began (the longest baseline);
        # tracks still short of parallax carry their origin on to the new key frame
        new = np.flatnonzero(~known)
        if len(new):
            kf_idx = len(self.keyframes) - 1
            okf = np.where(kf.origin_kf[ik[new]] >= 0, kf.origin_kf[ik[new]], kf_idx)
            ofeat = np.where(kf.origin_kf[ik[new]] >= 0, kf.origin_feat[ik[new]], ik[new])
            for o in np.unique(okf):
                sel = np.flatnonzero(okf == o)
                src = self.keyframes[int(o)]
                X, ok = triangulate(self.K, src.T_cw, T_cw, src.feats.uv[ofeat[sel]], feats.uv[ic[new[sel]]],
                                    self.cfg.min_parallax_deg, self.cfg.max_depth_m, self.cfg.inlier_px)
                if ok.any():
                    ids = self._add_points(X[ok])
                    src.pid[ofeat[sel[ok]]] = ids
                    kf.pid[ik[new[sel[ok]]]] = ids
                    pid[ic[new[sel[ok]]]] = ids
                rest = sel[~ok]
                origin_kf[ic[new[rest]]] = o
                origin_feat[ic[new[rest]]] = ofeat[rest]
        self.keyframes.append(KeyFrame(index, stamp, feats, pid, T_cw, origin_kf, origin_feat))
        self._since_kf = 0
        if self.cfg.ba and len(self.keyframes) >= 4:
            t0 = time.perf_counter()
            local_bundle_adjustment(self, self.cfg.ba_window, self.cfg.ba_optimise, self.cfg.ba_max_nfev)
            self.ba_seconds += time.perf_counter() - t0

    # -- outputs
    def keyframe_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(indices, T_world_camera (K, 4, 4)) of the key frames."""
        return (np.array([k.index for k in self.keyframes]),
                np.array([np.linalg.inv(k.T_cw) for k in self.keyframes]))


def local_bundle_adjustment(vo: MonoVO, window: int = 6, optimise: int = 2, max_nfev: int = 15) -> None:
    """Bundle adjustment over the last ``window`` key frames: the last ``optimise`` poses and the points
    they observe move; the older poses in the window hold the gauge (and the first two key frames,
    which carry the given scale, never move)."""
    kfs = vo.keyframes[-window:]
    first_free = max(len(vo.keyframes) - optimise, 2)
    offset = len(vo.keyframes) - len(kfs)
    free = [k for i, k in enumerate(kfs) if offset + i >= first_free]
    if not free:
        return
    pts = np.unique(np.concatenate([k.pid[k.pid >= 0] for k in free]))
    if len(pts) < 10:
        return
    P = vo.point_array()
    col = {int(p): i for i, p in enumerate(pts)}
    obs_f, obs_p, obs_uv = [], [], []
    for fi, k in enumerate(kfs):
        m = k.pid >= 0
        ids = k.pid[m]
        sel = np.isin(ids, pts)
        obs_f.append(np.full(int(sel.sum()), fi))
        obs_p.append(np.array([col[int(p)] for p in ids[sel]], dtype=int))
        obs_uv.append(k.feats.uv[m][sel])
    obs_f = np.concatenate(obs_f)
    obs_p = np.concatenate(obs_p)
    obs_uv = np.concatenate(obs_uv)
    free_idx = {id(k): j for j, k in enumerate(free)}
    frame_var = np.array([free_idx.get(id(k), -1) for k in kfs])
    nF, nP = len(free), len(pts)
    x0 = np.concatenate([np.concatenate([np.r_[_rotvec(k.T_cw[:3, :3]), k.T_cw[:3, 3]] for k in free]), P[pts].ravel()])
    fixed_R = np.array([k.T_cw[:3, :3] for k in kfs])
    fixed_t = np.array([k.T_cw[:3, 3] for k in kfs])
    K = vo.K

    def unpack(x):
        R = fixed_R.copy()
        t = fixed_t.copy()
        for fi in range(len(kfs)):
            j = frame_var[fi]
            if j >= 0:
                R[fi] = _rotmat(x[6 * j:6 * j + 3])
                t[fi] = x[6 * j + 3:6 * j + 6]
        return R, t, x[6 * nF:].reshape(nP, 3)

    def resid(x):
        R, t, X = unpack(x)
        Xc = np.einsum("nij,nj->ni", R[obs_f], X[obs_p]) + t[obs_f]
        z = np.where(np.abs(Xc[:, 2]) < 1e-6, 1e-6, Xc[:, 2])
        u = K[0, 0] * Xc[:, 0] / z + K[0, 2]
        v = K[1, 1] * Xc[:, 1] / z + K[1, 2]
        return np.column_stack([u - obs_uv[:, 0], v - obs_uv[:, 1]]).ravel()

    m = 2 * len(obs_f)
    S = lil_matrix((m, 6 * nF + 3 * nP), dtype=int)
    rows = np.arange(len(obs_f))
    for c in range(3):
        S[2 * rows, 6 * nF + 3 * obs_p + c] = 1
        S[2 * rows + 1, 6 * nF + 3 * obs_p + c] = 1
    fv = frame_var[obs_f]
    r = rows[fv >= 0]
    for c in range(6):
        S[2 * r, 6 * fv[fv >= 0] + c] = 1
        S[2 * r + 1, 6 * fv[fv >= 0] + c] = 1
    try:
        sol = least_squares(resid, x0, jac_sparsity=S, method="trf", loss="huber", f_scale=vo.cfg.inlier_px,
                            x_scale="jac", max_nfev=max_nfev)
    except ValueError as exc:  # degenerate problem: keep the estimates
        log.debug("bundle adjustment skipped: %s", exc)
        return
    if not np.all(np.isfinite(sol.x)) or sol.cost > 0.5 * np.sum(resid(x0) ** 2) * 1.0001:
        return
    R, t, X = unpack(sol.x)
    for fi, k in enumerate(kfs):
        if frame_var[fi] >= 0:
            k.T_cw = _rt_to_T(R[fi], t[fi])
    for i, p in enumerate(pts):
        vo.points[int(p)] = X[i]


def run_sequence(grays, stamps, K, image_size, method: str, baseline_m: float, seed: int = 0,
                 cfg: MonoConfig | None = None, init_gap: int = 20, features: list[Features] | None = None,
                 stop_on_failure: bool = True) -> MonoVO:
    """Run the monocular pipeline over a sequence: frames 0 and ``init_gap`` initialise with the given
    baseline; every later frame is tracked. ``features`` (precomputed per frame) skips detection."""
    cfg = cfg or MonoConfig()
    vo = MonoVO(K, image_size, method, cfg, seed)
    feat_secs = [0.0] * len(stamps)
    if features is None:
        features = []
        for i, g in enumerate(grays):
            t0 = time.perf_counter()
            features.append(detect_features(g, cfg))
            feat_secs[i] = time.perf_counter() - t0
    if not vo.initialise(features[0], features[init_gap], baseline_m, 0, init_gap, stamps[0], stamps[init_gap]):
        vo.failed = True
        return vo
    for i in range(init_gap + 1, len(stamps)):
        vo.process(features[i], i, stamps[i], feat_secs[i])
        if vo.failed and stop_on_failure:
            break
    return vo
