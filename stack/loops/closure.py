"""Loop closure: key frames, candidates from place recognition, LiDAR verification
(``stack.loops.verification``), a pose graph.

KISS-ICP is odometry only: on a long or looping route its ``T_map_base`` drifts. This module adds
what RTAB-Map adds on top of odometry:

1. **Key frames.** One camera image in ten (the topological-map paper) becomes a key frame, attached to the next
   registered LiDAR scan (its deskewed points in ``base_link`` and its odometry pose). Without a
   camera stream, every tenth scan is a LiDAR-only key frame.
2. **Candidates.** A described key frame queries the vocabulary-tree database
   (:mod:`stack.loops.place_recognition`) for the best-scoring *earlier* key frames, skipping the recent
   ones (same place because the robot has not moved on, not because it came back). A key frame
   without a description (a black image in the dark, a featureless wall) proposes instead the key
   frames near its current pose estimate (LiDAR-only fallback); ``proximity = "always"`` does both.
3. **Geometric verification.** The two scans are registered by a point-to-plane ICP (scipy KD-tree,
   robust weights; x, y and yaw for a ground robot), starting from the relative pose the corrected
   odometry predicts. The candidate is accepted only if enough of the query's wall and furniture
   points land on the candidate's surfaces (inlier fraction, RMSE), the matched surfaces face enough
   directions and the solution is unique (restarted off to the side, ICP comes back: a bare corridor
   slides along itself), and the correction is one the odometry could have drifted (bounded by the
   path driven between the two key frames): a false closure is worse than none.
4. **Pose graph.** Key frames are nodes, consecutive key frames are joined by odometry edges and
   verified candidates by loop edges (Huber kernel); GTSAM's iSAM2 keeps it optimised online, and
   ``finalise`` runs a batch Levenberg-Marquardt at the end of a run.
5. **Corrected trajectory.** For any time, ``T_map_base = C(t) @ T_map_base_odometry(t)`` with the
   correction ``C = T_optimised @ inv(T_odometry)`` interpolated between key frames. Everything placed
   with the odometry (object labels) can be re-placed with this trajectory, so labels made before a
   closure move with it.

``map`` stays the odometry's ``map`` (the first key frame is held by a prior).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from stack.loops.place_recognition import FeatureConfig, KeyFrameFeatures, PlaceDatabase, VocabularyTree, describe
from stack.loops.verification import Verification, _voxel_down, surface_normals, verify  # noqa: F401 (re-exported)
from stack.transforms import inv, interpolate_trajectory

log = logging.getLogger(__name__)


class LoopClosureConfig(BaseModel):
    """Defaults tuned for an indoor Jackal (32-beam LiDAR, D435i colour at 10 Hz, <= 2 m/s)."""

    model_config = ConfigDict(extra="forbid")

    # key frames
    keyframe_every: int = Field(10, ge=1, description="one camera image in this many is a key frame (seed 001)")
    scan_keyframe_every: int = Field(10, ge=1, description="without images: one scan in this many is a key frame")
    image_timeout_s: float = Field(2.0, gt=0, description="no image for this long: LiDAR-only key frames")
    keyframe_voxel_m: float = Field(0.15, gt=0, description="key-frame scans are kept at this resolution")
    # candidates
    skip_recent_s: float = Field(20.0, ge=0, description="key frames newer than this are not candidates ...")
    skip_recent_m: float = Field(6.0, ge=0, description="... nor those fewer metres of path back")
    top_k: int = Field(3, ge=1, description="best retrieval matches verified per key frame")
    closure_every_m: float = Field(2.0, ge=0, description="after a closure, search again after this much path")
    min_score: float = Field(0.05, ge=0, le=1, description="TF-IDF cosine below this is not a candidate")
    proximity: Literal["fallback", "always", "never"] = Field(
        "fallback", description="candidates by pose proximity: for undescribed key frames, always, or never")
    proximity_radius_m: float = Field(2.5, gt=0, description="search radius around the pose estimate")
    proximity_max: int = Field(1, ge=0, description="nearest key frames verified by proximity")
    # verification
    icp_voxel_m: float = Field(0.3, gt=0, description="the query scan is sampled at this voxel for ICP")
    icp_max_iterations: int = Field(30, ge=1, description="per correspondence distance")
    icp_coarse_m: float = Field(1.0, gt=0, description="correspondence distance of the first ICP pass")
    icp_fine_m: float = Field(0.3, gt=0, description="correspondence distance of the second pass")
    inlier_m: float = Field(0.3, gt=0, description="a query point within this of a candidate point ...")
    inlier_plane_m: float = Field(0.06, gt=0, description="... and this of its surface (along its normal) is an inlier")
    vertical_max_nz: float = Field(0.3, gt=0, le=1, description="a point whose normal has |z| below this is on a "
                                   "vertical surface (structure); floor and ceiling match anywhere")
    min_inlier_fraction: float = Field(0.7, gt=0, le=1, description="of the query's structure points")
    max_inlier_rmse_m: float = Field(0.035, gt=0, description="of the inliers' surface distances")
    min_points: int = Field(300, ge=10, description="fewer points in either scan: not verifiable")
    min_constraint: float = Field(0.03, ge=0, le=0.5, description="weakest horizontal direction's share of the "
                                  "matched structure normals (0: a bare corridor, 0.5: isotropic)")
    basin_shift_m: float = Field(0.5, gt=0, description="uniqueness: ICP restarted this far off along x and y ...")
    basin_tolerance_m: float = Field(0.1, gt=0, description="... must come back within this of the solution")
    max_correction_m: float = Field(0.4, ge=0, description="ICP may move the predicted relative pose by this ...")
    max_correction_per_m: float = Field(0.02, ge=0, description="... plus this per metre of path between them ...")
    max_correction_cap_m: float = Field(2.0, gt=0, description="... up to this")
    max_place_distance_m: float = Field(3.0, gt=0, description="two key frames further apart than this (after "
                                        "the drift allowance) are not one place")
    max_rotation_deg: float = Field(4.0, ge=0)
    max_rotation_deg_per_m: float = Field(0.1, ge=0)
    max_rotation_cap_deg: float = Field(15.0, gt=0)
    # pose graph (sigmas of the edges)
    odom_sigma_m: float = Field(0.01, gt=0, description="odometry edge: translation sigma ...")
    odom_sigma_per_m: float = Field(0.02, ge=0, description="... plus this per metre driven")
    odom_sigma_rad: float = Field(0.002, gt=0, description="odometry edge: rotation sigma ...")
    odom_sigma_rad_per_m: float = Field(0.004, ge=0, description="... plus this per metre ...")
    odom_sigma_rad_per_rad: float = Field(0.01, ge=0, description="... plus this per radian turned")
    loop_sigma_m: float = Field(0.05, gt=0)
    loop_sigma_rad: float = Field(0.01, gt=0)
    odom_sigma_per_mps: float = Field(0.3, ge=0, description="odometry edge: translation sigma added per m/s "
                                      "of speed change (a constant-velocity prediction is worst there)")
    planar: bool = Field(True, description="ground robot on one floor: registration and loop edges in x, y and "
                         "yaw only; height, roll and pitch stay the odometry's (it levels on the floor; a small "
                         "pitch error in a registration would otherwise tilt a long corridor)")
    planar_sigma_m: float = Field(1.0, gt=0, description="loop-edge sigma of z when planar")
    planar_sigma_rad: float = Field(0.2, gt=0, description="loop-edge sigma of roll and pitch when planar")
    loop_huber_k: float = Field(3.0, gt=0, description="Huber kernel on loop edges (whitened units)")
    features: FeatureConfig = Field(default_factory=FeatureConfig)


@dataclass
class KeyFrame:
    index: int
    stamp: float  # of its scan (end of sweep), s
    T_odom: np.ndarray  # T_map_base from odometry at stamp
    points_base: np.ndarray  # (N, 3) float32 scan points in base_link
    path_m: float  # odometry path length driven up to stamp
    described: bool
    image_stamp: float | None = None
    normals: np.ndarray | None = None  # of points_base, computed when first needed

    def get_normals(self) -> np.ndarray:
        if self.normals is None:
            self.normals = surface_normals(self.points_base)
        return self.normals


@dataclass
class LoopClosure:
    query: int
    candidate: int
    query_stamp: float
    candidate_stamp: float
    source: str  # "appearance" or "proximity"
    score: float | None
    T_cand_query: np.ndarray
    inlier_fraction: float
    correction_m: float

    def as_dict(self) -> dict:
        return {"query_stamp": self.query_stamp, "candidate_stamp": self.candidate_stamp, "source": self.source,
                "score": self.score, "inlier_fraction": self.inlier_fraction, "correction_m": self.correction_m,
                "T_cand_query": np.round(self.T_cand_query, 6).tolist()}


@dataclass
class LoopStats:
    key_frames: int = 0
    described: int = 0
    candidates_appearance: int = 0
    candidates_proximity: int = 0
    accepted: int = 0
    rejected: int = 0
    rejections: dict = field(default_factory=dict)  # reason -> count
    optimisations: int = 0
    seconds_describe: float = 0.0
    seconds_retrieve: float = 0.0
    seconds_verify: float = 0.0
    seconds_optimise: float = 0.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


# ---------------------------------------------------------------------------------------------
# pose graph

GTSAM_MISSING = ("loop closure needs GTSAM, an optional dependency: pip install 'dopeslam-testbed[loops]' "
                 "(or pip install gtsam)")


def require_gtsam():
    """The ``gtsam`` module, or a ModuleNotFoundError that says how to install it."""
    try:
        import gtsam
    except ModuleNotFoundError as exc:
        if exc.name != "gtsam":
            raise
        raise ModuleNotFoundError(GTSAM_MISSING, name="gtsam") from None
    return gtsam


def _pose3(T: np.ndarray):
    gtsam = require_gtsam()

    return gtsam.Pose3(np.asarray(T, dtype=float))


def _noise(sig):
    gtsam = require_gtsam()

    s = np.asarray(sig, dtype=float)
    return gtsam.noiseModel.Diagonal.Sigmas(np.concatenate([s[3:], s[:3]]))  # GTSAM: rotation first


PRIOR_SIGMAS = np.array([1e-6] * 3 + [1e-8] * 3)


def optimise_pose_graph(T_init: np.ndarray, odom_edges: list[tuple[int, int, np.ndarray, np.ndarray]],
                        loop_edges: list[tuple[int, int, np.ndarray, np.ndarray]], huber_k: float = 3.0,
                        max_iterations: int = 100) -> np.ndarray:
    """Levenberg-Marquardt (GTSAM) over SE(3) nodes.

    ``T_init`` (N, 4, 4) initial node poses; node 0 is held. Edges are ``(i, j, T_i_j, sigmas)`` with
    sigmas (6,) = (tx, ty, tz, rx, ry, rz) in metres and radians; loop edges get a Huber kernel.
    Returns the optimised poses (N, 4, 4).
    """
    gtsam = require_gtsam()

    noise = _noise
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, T in enumerate(T_init):
        values.insert(i, _pose3(T))
    graph.add(gtsam.PriorFactorPose3(0, _pose3(T_init[0]), noise(PRIOR_SIGMAS)))
    for i, j, T_ij, sig in odom_edges:
        graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_ij), noise(sig)))
    huber = gtsam.noiseModel.mEstimator.Huber.Create(huber_k)
    for i, j, T_ij, sig in loop_edges:
        graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_ij), gtsam.noiseModel.Robust.Create(huber, noise(sig))))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.array([result.atPose3(i).matrix() for i in range(len(T_init))])


# ---------------------------------------------------------------------------------------------


class LoopCloser:
    """Feed it odometry-registered scans and camera images in time order; it keeps a corrected trajectory.

    ``vocabulary`` may be None: then no appearance retrieval, only proximity candidates (if enabled).
    """

    def __init__(self, vocabulary: VocabularyTree | None, config: LoopClosureConfig | None = None):
        self.config = config or LoopClosureConfig()
        self.vocabulary = vocabulary
        self.database = PlaceDatabase(vocabulary) if vocabulary is not None else None
        self.key_frames: list[KeyFrame] = []
        self.T_opt: list[np.ndarray] = []  # optimised T_map_base per key frame
        self.closures: list[LoopClosure] = []
        self.rejected: list[dict] = []
        self.stats = LoopStats()
        self._loop_edges: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        self._images = 0
        self._pending: tuple[float, KeyFrameFeatures | None] | None = None
        self._last_image_stamp: float | None = None
        self._scans_since_key = 0
        self._path_m = 0.0
        self._last_T: np.ndarray | None = None
        self._next_search_m = 0.0  # after a closure, the next search waits until the path passes this
        self._isam = None

    # ------------------------------------------------------------------ input

    def add_image(self, stamp: float, rgb: np.ndarray | None) -> None:
        """A camera image (RGB uint8). Every ``keyframe_every``-th becomes a key frame at the next scan."""
        self._last_image_stamp = float(stamp)
        take = self._images % self.config.keyframe_every == 0
        self._images += 1
        if not take:
            return
        feats = None
        if rgb is not None and self.vocabulary is not None:
            t0 = time.perf_counter()
            feats = describe(rgb, self.config.features)
            self.stats.seconds_describe += time.perf_counter() - t0
        self._pending = (float(stamp), feats)

    def add_scan(self, stamp: float, T_map_base: np.ndarray, points_base: np.ndarray) -> LoopClosure | None:
        """An odometry-registered scan: its pose stamp, odometry ``T_map_base`` and points in ``base_link``.
        Returns the first loop closure accepted at this scan, if any."""
        T_map_base = np.asarray(T_map_base, dtype=float)
        points_base = np.zeros((0, 3)) if points_base is None else points_base
        if self._last_T is not None:
            self._path_m += float(np.linalg.norm(T_map_base[:3, 3] - self._last_T[:3, 3]))
        self._last_T = T_map_base
        self._scans_since_key += 1
        no_camera = self._last_image_stamp is None or stamp - self._last_image_stamp > self.config.image_timeout_s
        if self._pending is not None:
            img_stamp, feats = self._pending
            self._pending = None
            return self._add_key_frame(stamp, T_map_base, points_base, feats, img_stamp)
        if no_camera and (not self.key_frames or self._scans_since_key >= self.config.scan_keyframe_every):
            return self._add_key_frame(stamp, T_map_base, points_base, None, None)
        return None

    # ------------------------------------------------------------------ output

    def corrections(self) -> tuple[np.ndarray, np.ndarray]:
        """(key-frame stamps (K,), corrections C = T_opt @ inv(T_odom) (K, 4, 4))."""
        if not self.key_frames:
            return np.zeros(0), np.zeros((0, 4, 4))
        st = np.array([k.stamp for k in self.key_frames])
        C = np.array([T @ inv(k.T_odom) for T, k in zip(self.T_opt, self.key_frames)])
        return st, C

    def correct(self, stamps, T_map_base_odom: np.ndarray) -> np.ndarray:
        """Corrected ``T_map_base`` for odometry poses (N, 4, 4) (or one 4x4) at ``stamps``."""
        T = np.asarray(T_map_base_odom, dtype=float)
        single = T.ndim == 2
        T = T[None] if single else T
        st, C = self.corrections()
        if len(st) == 0:
            out = T.copy()
        else:
            Ct = interpolate_trajectory(st, C, np.atleast_1d(np.asarray(stamps, dtype=float)))
            out = Ct @ T
        return out[0] if single else out

    def summary(self) -> dict:
        return {"loop_closures": len(self.closures), "loop_candidates_rejected": self.stats.rejected,
                "key_frames": self.stats.key_frames, "key_frames_described": self.stats.described,
                "rejection_reasons": dict(self.stats.rejections),
                "closures_by_source": {s: sum(c.source == s for c in self.closures)
                                       for s in ("appearance", "proximity")},
                "seconds": {k: v for k, v in self.stats.as_dict().items() if k.startswith("seconds")}}

    # ------------------------------------------------------------------ internals

    def _add_key_frame(self, stamp, T_map_base, points_base, feats, img_stamp) -> LoopClosure | None:
        cfg = self.config
        pts = np.asarray(points_base, dtype=np.float64).reshape(-1, 3)
        if len(pts):
            pts = _voxel_down(pts, cfg.keyframe_voxel_m)
        kf = KeyFrame(len(self.key_frames), float(stamp), T_map_base.copy(), pts.astype(np.float32), self._path_m,
                      feats is not None, img_stamp)
        # the new node's estimate: the last correction carried forward on odometry
        C_last = self.T_opt[-1] @ inv(self.key_frames[-1].T_odom) if self.key_frames else np.eye(4)
        self.key_frames.append(kf)
        self.T_opt.append(C_last @ kf.T_odom)
        self._scans_since_key = 0
        self.stats.key_frames += 1
        self.stats.described += int(kf.described)
        if self.database is not None:
            self.database.add(feats.descriptors if feats is not None else None)
        n_loops = len(self._loop_edges)
        first = self._close_loops(kf, feats) if kf.path_m >= self._next_search_m else None
        self._update_graph(kf, self._loop_edges[n_loops:])
        if first is not None:
            self._next_search_m = kf.path_m + cfg.closure_every_m
        return first

    def _eligible(self, kf: KeyFrame) -> int:
        """Key frames [0, n) are old enough (in time and path) to be loop candidates of ``kf``."""
        cfg = self.config
        n = 0
        for k in self.key_frames[:-1]:
            if k.stamp <= kf.stamp - cfg.skip_recent_s and k.path_m <= kf.path_m - cfg.skip_recent_m:
                n = k.index + 1
            else:
                break
        return n

    def _close_loops(self, kf: KeyFrame, feats: KeyFrameFeatures | None) -> LoopClosure | None:
        cfg = self.config
        n = self._eligible(kf)
        if n == 0:
            return None
        cands: list[tuple[int, str, float | None]] = []
        if feats is not None and self.database is not None:
            t0 = time.perf_counter()
            for m in self.database.query(feats.descriptors, k=cfg.top_k, before=n, min_score=cfg.min_score):
                cands.append((m.key_frame, "appearance", m.score))
            self.stats.seconds_retrieve += time.perf_counter() - t0
            self.stats.candidates_appearance += len(cands)
        if cfg.proximity == "always" or (cfg.proximity == "fallback" and feats is None):
            here = self.T_opt[-1][:3, 3]
            pos = np.array([T[:3, 3] for T in self.T_opt[:n]])
            d = np.linalg.norm(pos - here, axis=1)
            near = [int(i) for i in np.argsort(d)[:cfg.proximity_max] if d[i] <= cfg.proximity_radius_m]
            new = [i for i in near if all(i != c[0] for c in cands)]
            cands += [(i, "proximity", None) for i in new]
            self.stats.candidates_proximity += len(new)
        first = None
        for ci, source, score in cands:
            cand = self.key_frames[ci]
            T_init = inv(self.T_opt[ci]) @ self.T_opt[-1]
            t0 = time.perf_counter()
            v = verify(kf.points_base, cand.points_base, T_init, kf.path_m - cand.path_m, cfg,
                       kf.get_normals(), cand.get_normals())
            self.stats.seconds_verify += time.perf_counter() - t0
            if not v.accepted:
                self.stats.rejected += 1
                self.stats.rejections[v.reason] = self.stats.rejections.get(v.reason, 0) + 1
                self.rejected.append({"query_stamp": kf.stamp, "candidate_stamp": cand.stamp, "source": source,
                                      "score": score, "reason": v.reason, "inlier_fraction": v.inlier_fraction,
                                      "correction_m": v.correction_m, "T_cand_query": v.T_cand_query})
                continue
            lc = LoopClosure(kf.index, ci, kf.stamp, cand.stamp, source, score, v.T_cand_query, v.inlier_fraction,
                             v.correction_m)
            self.closures.append(lc)
            self.stats.accepted += 1
            sig = [cfg.loop_sigma_m] * 3 + [cfg.loop_sigma_rad] * 3
            if cfg.planar:
                sig = [cfg.loop_sigma_m, cfg.loop_sigma_m, cfg.planar_sigma_m, cfg.planar_sigma_rad,
                       cfg.planar_sigma_rad, cfg.loop_sigma_rad]
            self._loop_edges.append((ci, kf.index, v.T_cand_query, np.array(sig)))
            first = first or lc
        return first

    def _odom_edge(self, a: KeyFrame, b: KeyFrame) -> tuple[int, int, np.ndarray, np.ndarray]:
        """Odometry between consecutive key frames; its sigmas grow with the distance and angle."""
        cfg = self.config
        T_ab = inv(a.T_odom) @ b.T_odom
        d = float(np.linalg.norm(T_ab[:3, 3]))
        th = float(np.linalg.norm(Rotation.from_matrix(T_ab[:3, :3]).as_rotvec()))
        st = cfg.odom_sigma_m + cfg.odom_sigma_per_m * d
        if cfg.odom_sigma_per_mps > 0 and a.index > 0 and b.stamp > a.stamp:
            p = self.key_frames[a.index - 1]
            v_before = np.linalg.norm(a.T_odom[:3, 3] - p.T_odom[:3, 3]) / max(a.stamp - p.stamp, 1e-3)
            st += cfg.odom_sigma_per_mps * abs(d / (b.stamp - a.stamp) - v_before)
        sr = cfg.odom_sigma_rad + cfg.odom_sigma_rad_per_m * d + cfg.odom_sigma_rad_per_rad * th
        return a.index, b.index, T_ab, np.array([st, st, st, sr, sr, sr])

    def _update_graph(self, kf: KeyFrame, loops: list) -> None:
        """Add the key frame (and its loop edges) to the incremental solver (GTSAM's iSAM2)."""
        gtsam = require_gtsam()

        t0 = time.perf_counter()
        if self._isam is None:
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(0.01)
            self._isam = gtsam.ISAM2(params)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if kf.index == 0:
            graph.add(gtsam.PriorFactorPose3(0, _pose3(self.T_opt[0]), _noise(PRIOR_SIGMAS)))
        else:
            i, j, T_ij, sig = self._odom_edge(self.key_frames[kf.index - 1], kf)
            graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_ij), _noise(sig)))
        values.insert(kf.index, _pose3(self.T_opt[kf.index]))
        huber = gtsam.noiseModel.mEstimator.Huber.Create(self.config.loop_huber_k)
        for i, j, T_ij, sig in loops:
            graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_ij), gtsam.noiseModel.Robust.Create(huber, _noise(sig))))
        self._isam.update(graph, values)
        if loops:
            for _ in range(3):
                self._isam.update()
            est = self._isam.calculateEstimate()
            self.T_opt = [est.atPose3(i).matrix() for i in range(len(self.key_frames))]
            self.stats.optimisations += 1
        self.stats.seconds_optimise += time.perf_counter() - t0

    def finalise(self) -> None:
        """A last batch optimisation (Levenberg-Marquardt over the whole graph) after the run."""
        if not self._loop_edges:
            return
        t0 = time.perf_counter()
        edges = [self._odom_edge(a, b) for a, b in zip(self.key_frames[:-1], self.key_frames[1:])]
        T = optimise_pose_graph(np.array(self.T_opt), edges, self._loop_edges, self.config.loop_huber_k)
        self.T_opt = list(T)
        self.stats.optimisations += 1
        self.stats.seconds_optimise += time.perf_counter() - t0
