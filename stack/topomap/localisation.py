"""Localisation against the semantic topological map (``stack.topomap.topological_map``): retrieval
by the vocabulary tree, then a metric fix by a pose estimator (ORPE by default) against a node's
triangulated points (``localise``); places seen on two passes joined by ``revisit`` edges
(``add_revisit_edges``); relative poses up to scale from the essential matrix
(``relative_pose_up_to_scale``), points from an image pair with a known baseline
(``points_from_pair``) and a pose against such points (``pose_against_points``), which navigation
uses against the mapping run's images.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stack.topomap.mono_pose import Features, MonoConfig, detect_features, grunert, orpe, triangulate
from stack.topomap.topological_map import REVISIT, TopoMap
from stack.transforms import inv


@dataclass
class Fix:
    node: int
    score: float  # retrieval score
    T_map_camera: np.ndarray
    inliers: int


def match_global(a: Features, b: Features, max_dist: float = 0.4, ratio: float = 0.85) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest descriptors with a ratio test (no search region: the relative pose is unknown)."""
    if len(a) < 2 or len(b) < 2:
        e = np.zeros(0, dtype=int)
        return e, e
    d2 = np.maximum(2.0 - 2.0 * a.desc @ b.desc.T, 0.0)
    j = np.argmin(d2, axis=1)
    part = np.partition(d2, 1, axis=1)
    best, second = part[:, 0], part[:, 1]
    i = np.arange(len(a))
    back = np.argmin(d2, axis=0)
    ok = (np.sqrt(best) < max_dist) & (best < ratio ** 2 * second) & (back[j] == i)
    return i[ok], j[ok]


def localise(topo: TopoMap, rgb: np.ndarray, tree, k: int = 3, method: str = "orpe",
             rng: np.random.Generator | None = None, cfg: MonoConfig | None = None,
             feats: Features | None = None, candidates: list[int] | None = None) -> Fix | None:
    """Where the camera is in the map: retrieval proposes nodes (vocabulary tree, TF-IDF), then the
    pose relative to the best node that verifies (its points, ORPE or Grunert in RANSAC)."""
    import cv2

    from stack.loops.place_recognition import describe

    cfg = cfg or MonoConfig()
    rng = rng or np.random.default_rng(0)
    if candidates is None:
        f = describe(rgb)
        if f is None:
            return None
        cands = topo.retrieve(tree, f.descriptors, k)
    else:
        cands = [(c, 0.0) for c in candidates]
    if feats is None:
        feats = detect_features(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), cfg)
    best = None
    for nid, score in cands:
        node = topo.nodes[nid]
        T_cam_map = inv(node.T_map_camera)
        X_node = node.points_map @ T_cam_map[:3, :3].T + T_cam_map[:3, 3]  # NaN rows stay NaN
        res = pose_against_points(topo.K, node.features, X_node, feats, rng, cfg, method)
        if res is None:
            continue
        fix = Fix(nid, score, node.T_map_camera @ res[0], res[1])
        if best is None or fix.inliers > best.inliers:
            best = fix
    return best


def add_revisit_edges(topo: TopoMap, tree, k: int = 5, min_gap_nodes: int = 20, min_inliers: int = 30,
                      seed: int = 0) -> int:
    """Join each node to the node of an earlier pass at the same place (a route driven twice): the
    vocabulary tree proposes ``k`` nodes at least ``min_gap_nodes`` earlier, the pose of the node's
    own features against their points (ORPE in RANSAC) verifies; the best verified one becomes a
    ``revisit`` edge with that relative pose. Returns the number of edges added; records
    ``meta['revisits']``."""
    rng = np.random.default_rng(seed)
    have = {(e.a, e.b) for e in topo.edges if e.kind == REVISIT}
    added = 0
    for n in topo.nodes:
        if n.place_desc is None or len(n.uv) < 8:
            continue
        cands = [c for c, _ in topo.retrieve(tree, n.place_desc, k) if c <= n.id - min_gap_nodes]
        if not cands:
            continue
        fix = localise(topo, None, tree, rng=rng, feats=n.features, candidates=cands)
        if fix is None or fix.inliers < min_inliers or (fix.node, n.id) in have:
            continue
        topo.add_edge(fix.node, n.id, REVISIT, inv(topo.nodes[fix.node].T_map_camera) @ fix.T_map_camera)
        have.add((fix.node, n.id))
        added += 1
    topo.meta["revisits"] = added
    return added


def _essential_pose(K: np.ndarray, ref: Features, feats: Features, cfg: MonoConfig, min_inliers: int):
    """The relative pose of two images up to scale: essential matrix in RANSAC (OpenCV) on mutual
    matches, decomposed with the cheirality check. Returns (the matched reference indices, their
    pixels in both images, R, unit t with x_cur = R x_ref + t, the inlier mask, inliers) or None."""
    import cv2

    i, j = match_global(ref, feats, cfg.max_descriptor_distance)
    if len(i) < min_inliers:
        return None
    a = np.ascontiguousarray(ref.uv[i], dtype=np.float64)
    b = np.ascontiguousarray(feats.uv[j], dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    try:
        E, mask = cv2.findEssentialMat(a, b, K, cv2.RANSAC, 0.999, 1.0)
    except cv2.error:  # a degenerate sample set (the five-point solver's polynomial vanishes): no fix
        return None
    if E is None or E.shape != (3, 3) or mask is None or int(mask.sum()) < min_inliers:
        return None
    n, R, t, inl = cv2.recoverPose(E, a, b, K, mask=mask.copy())
    if n < min_inliers:
        return None
    return i, a, b, R, t.ravel(), inl.ravel(), int(n)


def relative_pose_up_to_scale(K: np.ndarray, ref: Features, feats: Features, cfg: MonoConfig | None = None,
                              min_inliers: int = 15, points: np.ndarray | None = None
                              ) -> tuple[np.ndarray, np.ndarray, int, tuple[float, int] | None] | None:
    """The pose of the current camera relative to a reference image's (a node's, or any image's
    features), up to scale: essential matrix in RANSAC on mutual matches of all features, with or
    without 3D points. For a fix where too few points are matched for a metric pose. ``points``:
    the reference's 3D points in its camera frame (NaN where none); with them the translation's
    scale is estimated from each inlier that has a point (ORPE's one-point scale, the median).
    Returns (R_ref_cur, the current camera's direction from the reference's in the reference
    camera's frame (unit), inliers, (scale, points used) or None), or None."""
    cfg = cfg or MonoConfig()
    res = _essential_pose(K, ref, feats, cfg, min_inliers)
    if res is None:
        return None
    i, a, b, R, t, inl, n = res
    scale = None
    if points is not None:
        keep = (inl > 0) & np.isfinite(points[i][:, 0])
        if keep.sum() >= 3:
            P = points[i][keep] @ R.T  # the points rotated into the current camera, before translation
            xy = (np.c_[b[keep], np.ones(int(keep.sum()))] @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T)[:, :2]
            # x (P_z + s t_z) = P_x + s t_x  ->  s (x t_z - t_x) = P_x - x P_z (and the same in y)
            a_x, b_x = xy[:, 0] * t[2] - t[0], P[:, 0] - xy[:, 0] * P[:, 2]
            a_y, b_y = xy[:, 1] * t[2] - t[1], P[:, 1] - xy[:, 1] * P[:, 2]
            den = a_x ** 2 + a_y ** 2
            ok = den > 1e-6
            if ok.sum() >= 3:
                s = (a_x * b_x + a_y * b_y)[ok] / den[ok]
                scale = (float(np.median(s)), int(ok.sum()))
    return R.T, -R.T @ t, int(n), scale  # recoverPose gives x_cur = R x_ref + t


def points_from_pair(K: np.ndarray, ref: Features, other: Features, baseline_m: float, cfg: MonoConfig | None = None,
                     min_inliers: int = 20) -> np.ndarray | None:
    """3D points for a reference image's features, in its camera frame (metres; NaN where none), from a
    second image of the same place: the relative rotation and translation direction from the
    essential matrix (RANSAC on mutual matches), the translation's length ``baseline_m`` given (the
    wheel odometry between the two images on a straight). None when the pair does not verify."""
    cfg = cfg or MonoConfig()
    if baseline_m <= 0:
        raise ValueError(f"baseline_m: expected a positive length, got {baseline_m}")
    res = _essential_pose(K, ref, other, cfg, min_inliers)
    if res is None:
        return None
    i, a, b, R, t, inl, _ = res
    T2 = np.eye(4)
    T2[:3, :3], T2[:3, 3] = R, t * baseline_m  # x_other = R x_ref + t
    keep = inl > 0
    X, ok = triangulate(K, np.eye(4), T2, a[keep], b[keep], cfg.min_parallax_deg, cfg.max_depth_m, cfg.inlier_px)
    if ok.sum() < 8:
        return None
    out = np.full((len(ref), 3), np.nan)
    out[i[keep][ok]] = X[ok]
    return out


def pose_against_points(K: np.ndarray, ref: Features, points: np.ndarray, feats: Features, rng: np.random.Generator,
                        cfg: MonoConfig | None = None, method: str = "orpe") -> tuple[np.ndarray, int] | None:
    """The metric pose of the current camera relative to a reference image with 3D points (its camera
    frame, NaN where none): ORPE (or Grunert's P3P) in RANSAC on mutual matches. Returns (T_ref_cur,
    inliers) or None."""
    cfg = cfg or MonoConfig()
    has = np.isfinite(points[:, 0])
    if has.sum() < 8:
        return None
    sub = Features(ref.uv[has], ref.desc[has])
    i, j = match_global(sub, feats, cfg.max_descriptor_distance)
    if len(i) < 8:
        return None
    if method == "orpe":
        est = orpe(K, points[has][i], sub.uv[i], feats.uv[j], rng, cfg)
    else:
        est = grunert(K, points[has][i], feats.uv[j], rng, cfg)
    if est is None:
        return None
    T_cur_ref = np.eye(4)
    T_cur_ref[:3, :3], T_cur_ref[:3, 3] = est.R, est.t
    return inv(T_cur_ref), int(est.inliers.sum())
