"""Geometric verification of a loop-closure candidate (``stack.loops.closure``): the query's LiDAR key
frame registered to the candidate's by point-to-plane ICP (coarse, then fine), then judged: inliers
on vertical structure, their surface RMSE, how well the matched normals constrain both horizontal
directions, the uniqueness of the ICP basin (restarts shifted along x and y must come back), and
the correction's size against the odometry's drift allowance (``verify``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from stack.transforms import inv, make_T, transform_points

if TYPE_CHECKING:
    from stack.loops.closure import LoopClosureConfig


@dataclass
class Verification:
    accepted: bool
    reason: str  # "ok" or why not
    T_cand_query: np.ndarray  # registered relative pose (candidate base <- query base)
    inlier_fraction: float = 0.0
    inlier_rmse_m: float = float("nan")
    constraint: float = 0.0  # weakest horizontal direction's share of the matched structure normals
    basin_m: float = float("nan")  # farthest a shifted restart of ICP ended from the solution
    correction_m: float = float("nan")
    correction_deg: float = float("nan")



def _voxel_down(points: np.ndarray, voxel: float) -> np.ndarray:
    from kiss_icp.voxelization import voxel_down_sample

    return np.asarray(voxel_down_sample(np.ascontiguousarray(points, dtype=np.float64), voxel))


def _normals(tree: cKDTree, points: np.ndarray, k: int = 12, radius: float = 0.5) -> np.ndarray:
    """Unit surface normals by PCA of each point's k nearest neighbours within ``radius``; NaN where
    there are too few neighbours or they do not form a plane (a far wall sampled as separate scan lines
    looks like a line, whose "normal" is any direction perpendicular to it)."""
    k = min(k, len(points))
    d, idx = tree.query(points, k=k, distance_upper_bound=radius)
    ok = np.isfinite(d)
    idx = np.where(ok, idx, np.arange(len(points))[:, None])  # missing neighbours: the point itself
    cnt = ok.sum(1, keepdims=True)
    nb = points[idx]
    mean = (nb * ok[..., None]).sum(1) / cnt
    c = (nb - mean[:, None, :]) * ok[..., None]
    vals, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", c, c))
    normals = vecs[:, :, 0].copy()
    planar = (cnt[:, 0] >= 5) & (vals[:, 1] >= 0.05 * vals[:, 2]) & (vals[:, 0] <= 0.3 * vals[:, 1])
    normals[~planar] = np.nan
    return normals


def surface_normals(points: np.ndarray, band_m: float = 0.3) -> np.ndarray:
    """Normals (N, 3) of a scan in ``base_link`` for registration, NaN for points not to be used.

    Kept: horizontal surfaces (floor, ceiling: |n_z| > 0.95) and vertical ones (|n_z| < 0.3) more than
    ``band_m`` above the floor and below the ceiling. Dropped: everything else, in particular where a
    floor or ceiling scan ring meets a wall. There the neighbourhood mixes two surfaces into a plane
    that does not exist, and these points sit at the same place *relative to the sensor* in every scan:
    registration would lock onto the sensor's sampling pattern and call any two spots of a corridor
    the same place.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 5:
        return np.full((len(pts), 3), np.nan)
    n = _normals(cKDTree(pts), pts)
    with np.errstate(invalid="ignore"):
        nz = np.abs(n[:, 2])
        horizontal = nz > 0.95
        vertical = nz < 0.3
    z = pts[:, 2]
    floor = horizontal & (z < 0.3)
    ceiling = horizontal & (z > 1.0)
    lo = np.median(z[floor]) + band_m if floor.sum() >= 20 else -np.inf
    hi = np.median(z[ceiling]) - band_m if ceiling.sum() >= 20 else np.inf
    keep = horizontal | (vertical & (z > lo) & (z < hi))
    n[~keep] = np.nan
    return n


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())))


def _exp_se3_small(x: np.ndarray) -> np.ndarray:
    """Transform of the increment x = (omega, t) (rotation vector first), applied on the left."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


def icp_point_to_plane(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, T_init: np.ndarray,
                       tree: cKDTree | None = None, max_distances=(1.0, 0.6, 0.3), iterations: int = 30,
                       damping: float = 1e-3, planar: bool = False) -> np.ndarray:
    """Point-to-plane ICP (Gauss-Newton, Cauchy weights, Levenberg damping) of ``source`` onto ``target``
    from ``T_init`` (target <- source); one round per correspondence distance in ``max_distances``.
    ``planar``: only x, y and yaw move (height, roll and pitch stay those of ``T_init``).

    Point-to-plane rather than KISS-ICP's point-to-point: two scans taken metres apart sample the same
    wall at different densities, and point-to-point slides along a corridor by centimetres to decimetres
    before it stops, while point-to-plane residuals do not depend on the sampling.
    """
    tree = tree or cKDTree(target)
    T = np.asarray(T_init, dtype=float).copy()
    for dmax in max_distances:
        scale = dmax / 3
        for _ in range(iterations):
            p = transform_points(T, source)
            d, idx = tree.query(p, distance_upper_bound=dmax)
            m = np.isfinite(d)
            m[m] = np.isfinite(target_normals[idx[m]]).all(1)  # only targets on a plane
            if m.sum() < 6:
                break
            p, q, n = p[m], target[idx[m]], target_normals[idx[m]]
            r = np.einsum("ij,ij->i", p - q, n)
            J = np.hstack([np.cross(p, n), n])
            if planar:
                J = J[:, 2:5]  # yaw, x, y
            w = 1.0 / (1.0 + (r / scale) ** 2)
            H = J.T @ (J * w[:, None])
            g = J.T @ (w * r)
            step = -np.linalg.solve(H + damping * np.trace(H) / len(H) * np.eye(len(H)), g)
            dx = np.zeros(6)
            if planar:
                dx[2:5] = step
            else:
                dx = step
            T = _exp_se3_small(dx) @ T
            if np.linalg.norm(dx[3:]) < 1e-5 and np.linalg.norm(dx[:3]) < 1e-6:
                break
    return T


def verify(points_query: np.ndarray, points_cand: np.ndarray, T_init: np.ndarray, path_between_m: float,
           config: LoopClosureConfig | None = None, normals_query: np.ndarray | None = None,
           normals_cand: np.ndarray | None = None) -> Verification:
    """Register the query scan to the candidate scan (both in their own ``base_link``) from the predicted
    relative pose ``T_init`` (candidate <- query) and decide whether it is the same place.

    Floor and ceiling match anywhere, so the evidence is taken from the *structure*: query points on
    vertical surfaces (walls, furniture). Checks, in order: enough points; the share of structure
    points that land on the candidate's surfaces, and their RMSE; the matched surfaces' normals must
    span both horizontal directions, and the solution must be unique (ICP restarted half a metre off
    in x and in y comes back): a corridor of bare walls lets it slide along itself; the correction
    to ``T_init`` must be within what odometry drifts over ``path_between_m``. Before any ICP, a
    candidate the odometry places further away than that allowance plus ``max_place_distance_m`` is
    rejected as inconsistent with the odometry.
    """
    if config is None:
        from stack.loops.closure import LoopClosureConfig  # closure imports this module

        config = LoopClosureConfig()
    cfg = config
    T_init = np.asarray(T_init, dtype=float)
    allow_m = min(cfg.max_correction_cap_m, cfg.max_correction_m + cfg.max_correction_per_m * path_between_m)
    allow_deg = min(cfg.max_rotation_cap_deg, cfg.max_rotation_deg + cfg.max_rotation_deg_per_m * path_between_m)
    if np.linalg.norm(T_init[:2, 3]) > allow_m + cfg.max_place_distance_m:
        # the odometry puts them further apart than it can have drifted plus what one place spans:
        # whatever the images say, this is not a revisit it could register (cheap, before any ICP)
        return Verification(False, "inconsistent_with_odometry", T_init,
                            correction_m=float(np.linalg.norm(T_init[:2, 3])))
    pq = np.asarray(points_query, dtype=np.float64).reshape(-1, 3)
    pc = np.ascontiguousarray(np.asarray(points_cand, dtype=np.float64).reshape(-1, 3))
    if len(pq) < cfg.min_points or len(pc) < cfg.min_points:
        return Verification(False, "too_few_points", T_init)
    nc = surface_normals(pc) if normals_cand is None else normals_cand
    tree = cKDTree(pc)
    T = icp_point_to_plane(_voxel_down(pq, cfg.icp_voxel_m), pc, nc, T_init, tree,
                           (cfg.icp_coarse_m, (cfg.icp_coarse_m + cfg.icp_fine_m) / 2, cfg.icp_fine_m),
                           cfg.icp_max_iterations, planar=cfg.planar)

    nq = surface_normals(pq) if normals_query is None else normals_query
    with np.errstate(invalid="ignore"):  # NaN normals are not structure
        structure = np.abs(nq @ T[2, :3]) < cfg.vertical_max_nz  # the query's vertical surfaces, in the candidate
    moved = transform_points(T, pq)
    dist, nn = tree.query(moved, distance_upper_bound=cfg.inlier_m)
    found = np.isfinite(dist)
    nn = np.where(found, nn, 0)
    # distance to the candidate's surface: along its normal where it has one, else to the point
    n_at = nc[nn]
    plane = np.abs(np.einsum("ij,ij->i", moved - pc[nn], np.nan_to_num(n_at)))
    dist = np.where(np.isfinite(n_at).all(1), plane, dist)
    inl = found & (dist <= cfg.inlier_plane_m)
    n_struct = int(structure.sum())
    delta = inv(T_init) @ T
    out = Verification(False, "ok", T, correction_m=float(np.linalg.norm(delta[:3, 3])),
                       correction_deg=_angle_deg(delta[:3, :3]))
    if n_struct < cfg.min_points // 3:
        out.reason = "too_little_structure"
        return out
    good = inl & structure
    out.inlier_fraction = float(good.sum() / n_struct)
    out.inlier_rmse_m = float(np.sqrt(np.mean(dist[good] ** 2))) if good.any() else float("nan")
    if out.inlier_fraction < cfg.min_inlier_fraction:
        out.reason = "low_overlap"
        return out
    if out.inlier_rmse_m > cfg.max_inlier_rmse_m:
        out.reason = "high_rmse"
        return out
    # the matched walls and furniture must face enough directions to pin the horizontal position
    n_xy = nc[nn[good]][:, :2]
    n_xy = n_xy[np.isfinite(n_xy).all(1)]
    out.constraint = float(np.linalg.eigvalsh(n_xy.T @ n_xy / n_struct)[0]) if len(n_xy) else 0.0
    if out.constraint < cfg.min_constraint:
        out.reason = "degenerate"
        return out
    # uniqueness: restarted from shifted guesses, ICP must come back to the same pose. A corridor of
    # bare walls lets it slide: any position along it fits as well as the true one.
    coarse = _voxel_down(pq, 2 * cfg.icp_voxel_m)
    ends = []
    for dx, dy in ((1, 0), (0, 1)):
        start = make_T(None, (dx * cfg.basin_shift_m, dy * cfg.basin_shift_m, 0.0)) @ T
        Ts = icp_point_to_plane(coarse, pc, nc, start, tree, (2.5 * cfg.basin_shift_m, cfg.icp_fine_m),
                                cfg.icp_max_iterations // 2, planar=cfg.planar)
        ends.append(float(np.linalg.norm(Ts[:3, 3] - T[:3, 3])))
        if ends[-1] > cfg.basin_tolerance_m:
            break
    out.basin_m = max(ends)
    if out.basin_m > cfg.basin_tolerance_m:
        out.reason = "degenerate"
        return out
    if out.correction_m > allow_m or out.correction_deg > allow_deg:
        out.reason = "inconsistent_with_odometry"
        return out
    out.accepted = True
    return out
