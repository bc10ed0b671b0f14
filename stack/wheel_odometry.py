"""Wheel odometry as the pipeline's odometry (``--odometry wheel``): the robot's own dead reckoning
in place of KISS-ICP, the baseline a LiDAR odometry is measured against.

It satisfies :class:`stack.interfaces.Odometry`: the pipeline gives it every
:class:`~stack.messages.WheelOdometry` message (``on_wheel_odometry``) and every LiDAR sweep
(``process``); each sweep registers the wheel pose at the sweep's stamp, so images wait for a pose
after their stamp exactly as with the LiDAR odometry. ``map`` is ``base_link`` at the first
registered sweep, as there. The sweep's points are used only for the LiDAR map picture.
"""
from __future__ import annotations

import numpy as np

from stack.lidar_slam import WheelOdometryTrack
from stack.messages import LidarScan, WheelOdometry
from stack.pose_track import PoseTrack
from stack.transforms import interpolate, interpolate_trajectory, inv, transform_points


class WheelOnlyOdometry:
    """``T_map_base`` from the wheel odometry alone. ``T_base_lidar``: the LiDAR's mounting (for the
    map picture; None: no points). ``max_extrapolation_s``: how far past the newest wheel message
    (or before the first sweep) a pose is given."""

    def __init__(self, T_base_lidar: np.ndarray | None = None, max_extrapolation_s: float = 0.2):
        self.T_base_lidar = None if T_base_lidar is None else np.asarray(T_base_lidar, dtype=float)
        self.max_extrapolation_s = float(max_extrapolation_s)
        self.wheel = WheelOdometryTrack()
        self.last_points_base: np.ndarray | None = None
        self._track = PoseTrack()  # T_map_base per registered sweep
        self._T_map_odom: np.ndarray | None = None  # inv(wheel pose at the first sweep)

    def __len__(self) -> int:
        return len(self._track)

    def on_wheel_odometry(self, msg: WheelOdometry) -> None:
        self.wheel.add(msg)

    def _wheel_at(self, t: float) -> np.ndarray | None:
        """The wheel pose (its own frame) at t: interpolated; extrapolated a little past the newest."""
        stamps, poses = self.wheel.stamps, self.wheel.poses
        if not len(stamps) or t < stamps[0] - self.max_extrapolation_s or t > stamps[-1] + self.max_extrapolation_s:
            return None
        if t <= stamps[-1] or len(stamps) < 2:
            return interpolate_trajectory(stamps, poses, t)
        alpha = (t - stamps[-2]) / (stamps[-1] - stamps[-2])
        return interpolate(poses[-2], poses[-1], alpha)

    def process(self, scan: LidarScan) -> np.ndarray | None:
        """The wheel pose at the sweep's stamp, in ``map``; None before any wheel odometry or when the
        sweep is not after the previous one."""
        t = float(scan.stamp)
        if self._track and t <= self._track.stamps[-1]:
            return None
        W = self._wheel_at(t)
        if W is None:
            return None
        if self._T_map_odom is None:
            self._T_map_odom = inv(W)
        pose = self._T_map_odom @ W
        self._track.append(t, pose)
        if self.T_base_lidar is not None and len(scan.points):
            self.last_points_base = transform_points(self.T_base_lidar, np.asarray(scan.points, dtype=float))
        return pose

    def pose_at(self, t: float) -> np.ndarray | None:
        """``T_map_base`` at t from the wheel track, within ``max_extrapolation_s`` of the registered
        sweeps; None elsewhere or before any sweep."""
        if not self._track:
            return None
        lim = self.max_extrapolation_s
        if t < self._track.stamps[0] - lim or t > self._track.stamps[-1] + lim:
            return None
        W = self._wheel_at(t)
        return None if W is None else self._T_map_odom @ W

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        return self._track.arrays()

    def last_stamp(self) -> float | None:
        """The newest registered pose's stamp (None before any)."""
        return float(self._track.stamps[-1]) if self._track else None

    def floor_plane_map(self):
        """No floor estimate (wheels see none): the object store checks no label against a floor."""
        return None
