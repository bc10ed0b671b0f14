"""Fusion: carry a DOPE pose from the camera into the map.

The whole idea is one chain of rigid transforms,

    T_map_obj = T_map_base(t_image) @ T_base_cam @ T_cam_obj

where ``T_map_base`` comes from LiDAR odometry, interpolated (SE(3)) at the image's
timestamp because images and scans are not taken at the same instants, ``T_base_cam``
is the camera's mounting (camera = colour optical frame: z forward, x right, y down)
and ``T_cam_obj`` is DOPE's PnP result.

The paper (section 3.3, eq. 1-2) writes the same thing as a hand-made homogeneous
transformation matrix (HTM) for flat ground and a level, forward-looking camera;
``paper_htm`` reproduces it and ``tests/unit/test_fusion.py`` shows the chain reduces to it.
"""
from __future__ import annotations

from typing import Callable, Union

import numpy as np

from stack.messages import Detection
from stack.object_store import Observation
from stack.transforms import interpolate

PoseLookup = Callable[[float], np.ndarray]
"""t (s) -> T_map_base (4x4)."""

Poses = Union[PoseLookup, tuple[np.ndarray, np.ndarray]]
"""A pose lookup, or (stamps (N,), T_map_base (N, 4, 4)) to interpolate."""


class PoseLookupError(LookupError):
    """No robot pose is known at the requested time (outside the recorded trajectory)."""


def trajectory_lookup(stamps, poses_T_map_base, tolerance_s: float = 0.0) -> PoseLookup:
    """A lookup interpolating a recorded trajectory.

    The pose at t is the SE(3) interpolation of the two poses around it. Up to
    ``tolerance_s`` beyond either end the end pose is used; further out PoseLookupError
    is raised rather than a stale pose returned: an image taken after the newest scan
    must wait for the next scan (a stale pose moves the label by the robot's speed
    times the delay).
    """
    stamps = np.asarray(stamps, dtype=float)
    poses = np.asarray(poses_T_map_base, dtype=float)
    if stamps.ndim != 1 or len(stamps) == 0 or poses.shape != (len(stamps), 4, 4):
        raise ValueError(f"trajectory: expected stamps (N,) and poses (N, 4, 4), got {stamps.shape} and {poses.shape}")
    if np.any(np.diff(stamps) <= 0):
        raise ValueError("trajectory: stamps must be strictly increasing")

    def lookup(t: float) -> np.ndarray:
        if not stamps[0] - tolerance_s <= t <= stamps[-1] + tolerance_s:
            raise PoseLookupError(f"no pose at t={t:.6f} s: trajectory covers {stamps[0]:.6f}..{stamps[-1]:.6f} s")
        if len(stamps) == 1 or t <= stamps[0]:
            return poses[0].copy()
        if t >= stamps[-1]:
            return poses[-1].copy()
        i = int(np.searchsorted(stamps, t))  # stamps[i - 1] < t <= stamps[i]
        return interpolate(poses[i - 1], poses[i], (t - stamps[i - 1]) / (stamps[i] - stamps[i - 1]))

    return lookup


def as_pose_lookup(poses: Poses) -> PoseLookup:
    if callable(poses):
        return poses
    stamps, T = poses
    return trajectory_lookup(stamps, T)


def chain(T_map_base: np.ndarray, T_base_cam: np.ndarray, T_cam_obj: np.ndarray) -> np.ndarray:
    """T_map_obj from the robot pose, the camera mounting and the object's pose in the camera."""
    return T_map_base @ T_base_cam @ T_cam_obj


def object_in_map(T_cam_obj: np.ndarray, stamp: float, poses: Poses, T_base_cam: np.ndarray) -> np.ndarray:
    """T_map_obj for an object seen at ``stamp`` (the image's time, seconds)."""
    return chain(as_pose_lookup(poses)(stamp), T_base_cam, T_cam_obj)


def fuse(detection: Detection, poses: Poses, T_base_cam: np.ndarray) -> Observation:
    """A DOPE detection as a map-frame observation, ready for the object store."""
    T_map_cam = as_pose_lookup(poses)(detection.stamp) @ T_base_cam
    return Observation.from_detection(detection, T_map_cam @ detection.T_cam_obj, T_map_cam)


# --- The paper's HTM (section 3.3), the flat-ground yaw-only special case -----------------------
#
# Eq. 2 as printed:
#     [x_map]   [ cos th   sin th   0   x_J ] [ x_cam     ]
#     [y_map] = [-sin th   cos th   0   x_J ] [ z_cam + d ]
#     [z_map]   [   0        0     -1   z_J ] [ y_cam     ]
#     [  1  ]   [   0        0      0    1  ] [ d         ]
# with eq. 1: th = 3 pi / 2 - Phi.
#
# What we assume (REP-103 map: x forward at start, y left, z up; DOPE's optical frame):
# * Row 2's translation is y_J (the printed x_J twice is a typo), and the vector's last entry is
#   1 (a printed d would scale the translation by d).
# * The camera looks along the robot's heading, level, on its centre line, d metres ahead of the
#   robot's reference point, and at the height z_J: the paper's z_Jackal is the camera's height
#   in the map (the matrix adds no height offset, only -y_cam, "down" -> "up").
# * The vector (x_cam, z_cam + d, y_cam) is (right, forward, down) in the robot's horizontal frame;
#   the matrix's upper-left block is a rotation by -th, and it places "forward" along the robot's
#   heading only when th = pi/2 - yaw, with yaw the usual counter-clockwise yaw from map +x.
#   Eq. 1's 3 pi / 2 - Phi is that angle when Phi = yaw + pi (Phi measured to the robot's rear,
#   or the map's axes turned half a turn); with Phi = yaw, eq. 1 puts every object behind the
#   robot, mirrored through the camera. ``htm_theta`` gives the angle for a REP-103 yaw.


def paper_theta(phi: float) -> float:
    """Eq. 1 as printed: th = 3 pi / 2 - Phi."""
    return 3.0 * np.pi / 2.0 - phi


def htm_theta(yaw: float) -> float:
    """The th that makes eq. 2 right for a REP-103 yaw (counter-clockwise from map +x)."""
    return np.pi / 2.0 - yaw


def paper_htm(p_cam, xyz_jackal, theta: float, d: float = 0.0) -> np.ndarray:
    """Eq. 2: an object's position in the camera (x right, y down, z forward) -> map position.

    ``xyz_jackal`` = (x_J, y_J, z_J), with z_J the camera's height (see the notes above).
    Only a position comes out: the HTM carries no object orientation.
    """
    x_cam, y_cam, z_cam = np.asarray(p_cam, dtype=float)
    x_J, y_J, z_J = np.asarray(xyz_jackal, dtype=float)
    c, s = np.cos(theta), np.sin(theta)
    htm = np.array([
        [c, s, 0.0, x_J],
        [-s, c, 0.0, y_J],
        [0.0, 0.0, -1.0, z_J],
        [0.0, 0.0, 0.0, 1.0],
    ])
    return (htm @ np.array([x_cam, z_cam + d, y_cam, 1.0]))[:3]
