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
    """The position and the quaternion (x, y, z, w) of a 4x4 transform.

    SciPy's ``Rotation.from_matrix`` takes the largest of the diagonal and the trace (Shepperd's
    method) and normalises, after checking the determinant and that the rotation is orthogonal to
    1e-12 (else it orthogonalises first). For one 4x4 whose rotation is orthogonal to 1e-13 (every
    product of rotations is, to about 1e-15) this does the same operations in the same order in
    plain floats, so the bits are SciPy's at about a twentieth of the cost (the map fusion calls it for
    every detection). Anything else (a looser rotation, a reflection, NaN, another shape) goes
    through SciPy itself, so its results and errors are SciPy's."""
    T = np.asarray(T)
    if T.shape == (4, 4) and T.dtype == np.float64:
        (m00, m01, m02, _), (m10, m11, m12, _), (m20, m21, m22, _), _ = T.tolist()
        # the Gram matrix R R^T against the identity, and the determinant's sign
        dev = max(abs(m00 * m00 + m01 * m01 + m02 * m02 - 1.0), abs(m10 * m10 + m11 * m11 + m12 * m12 - 1.0),
                  abs(m20 * m20 + m21 * m21 + m22 * m22 - 1.0), abs(m00 * m10 + m01 * m11 + m02 * m12),
                  abs(m00 * m20 + m01 * m21 + m02 * m22), abs(m10 * m20 + m11 * m21 + m12 * m22))
        det = m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20) + m02 * (m10 * m21 - m11 * m20)
        if dev < 1e-13 and det > 0.5:  # False for NaN
            tr = m00 + m11 + m22
            if m00 >= m11 and m00 >= m22 and m00 >= tr:  # the first largest, as NumPy's argmax picks it
                q = (1 - tr + 2 * m00, m10 + m01, m20 + m02, m21 - m12)
            elif m11 >= m22 and m11 >= tr:
                q = (m01 + m10, 1 - tr + 2 * m11, m21 + m12, m02 - m20)
            elif m22 >= tr:
                q = (m02 + m20, m12 + m21, 1 - tr + 2 * m22, m10 - m01)
            else:
                q = (m21 - m12, m02 - m20, m10 - m01, 1 + tr)
            n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
            return T[:3, 3].copy(), np.array([q[0] / n, q[1] / n, q[2] / n, q[3] / n])
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
