"""Homogeneous transforms. A 4x4 named ``T_a_b`` maps points in frame b to frame a.

Quaternions are (x, y, z, w), as in ROS and PyBullet.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def make_T(R: np.ndarray | None = None, t=None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float)
    return T


def inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def from_xyz_quat(xyz, quat_xyzw) -> np.ndarray:
    """The 4x4 transform of a position and a quaternion (x, y, z, w; normalised here).

    One quaternion is turned into its matrix in plain floats, with the operations SciPy's
    ``Rotation.from_quat(q).as_matrix()`` does in the same order, so the bits are the same at a
    fifth of the cost (the simulator calls this at every physics step). A zero, infinite or NaN
    norm, or any other shape, goes through SciPy itself, so its errors are SciPy's."""
    q = np.asarray(quat_xyzw, dtype=float)
    t = np.asarray(xyz, dtype=float)
    if q.shape == (4,) and t.shape == (3,):
        x, y, z, w = q.tolist()
        n = math.sqrt(x * x + y * y + z * z + w * w)
        if 0.0 < n < math.inf:
            x, y, z, w = x / n, y / n, z / n, w / n
            x2, y2, z2, w2 = x * x, y * y, z * z, w * w
            xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
            tx, ty, tz = t.tolist()
            return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw), tx],
                             [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw), ty],
                             [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2, tz],
                             [0.0, 0.0, 0.0, 1.0]])
    return make_T(Rotation.from_quat(q).as_matrix(), xyz)


def to_xyz_quat(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat()


def from_xyz_rpy(xyz, rpy) -> np.ndarray:
    return make_T(Rotation.from_euler("xyz", rpy).as_matrix(), xyz)


def yaw_of(T: np.ndarray) -> float:
    return float(np.arctan2(T[1, 0], T[0, 0]))


def wrap_angle(a: float) -> float:
    """An angle in radians brought into [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply T to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def voxel_thin(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """The first point in each voxel of size ``voxel_m`` (order kept)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        return points
    keys = np.floor(points / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


def interpolate(T0: np.ndarray, T1: np.ndarray, alpha: float) -> np.ndarray:
    """SE(3) interpolation: linear in translation, slerp in rotation (alpha may extrapolate a little)."""
    R0, R1 = Rotation.from_matrix(T0[:3, :3]), Rotation.from_matrix(T1[:3, :3])
    dR = (R0.inv() * R1).as_rotvec()
    R = R0 * Rotation.from_rotvec(alpha * dR)
    return make_T(R.as_matrix(), (1 - alpha) * T0[:3, 3] + alpha * T1[:3, 3])


def interpolate_trajectory(stamps: np.ndarray, poses: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Poses (N, 4, 4) at sorted ``stamps`` evaluated at ``t`` (clamped to the ends).

    Returns (4, 4) for a scalar t, else (M, 4, 4).
    """
    stamps = np.asarray(stamps, dtype=float)
    scalar = np.ndim(t) == 0
    tq = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), stamps[0], stamps[-1])
    if len(stamps) == 1:
        out = np.repeat(poses[:1], len(tq), axis=0)
        return out[0] if scalar else out
    if scalar and len(stamps) > 2:
        # one query: only its segment, the one scipy's Slerp picks (at a stamp: the segment ending
        # there, the first at the first stamp), so a lookup costs the same however long the
        # trajectory is; the same bits as the whole trajectory gives
        j = min(max(int(np.searchsorted(stamps, tq[0], side="left")) - 1, 0), len(stamps) - 2)
        stamps, poses = stamps[j:j + 2], np.asarray(poses)[j:j + 2]
    rots = Rotation.from_matrix(poses[:, :3, :3])
    slerp = Slerp(stamps, rots)
    out = np.tile(np.eye(4), (len(tq), 1, 1))
    out[:, :3, :3] = slerp(tq).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(tq, stamps, poses[:, k, 3])
    return out[0] if scalar else out
