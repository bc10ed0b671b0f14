"""Timestamped sensor and result messages exchanged between the world and the stack.

These are plain data types with no simulator knowledge: the simulator fills them,
a rosbag reader fills them, the stack consumes them. Times are float64 seconds;
the rosbag boundary converts to and from int nanoseconds.

Frame names follow DESIGN.md: ``map``, ``base_link``, ``velodyne``,
``camera_color_optical_frame`` (z forward, x right, y down).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class CameraInfo:
    """Pinhole intrinsics of an image stream (no distortion: the D435i colour stream is rectified)."""

    width: int
    height: int
    K: np.ndarray  # 3x3
    frame_id: str = "camera_color_optical_frame"

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @staticmethod
    def from_fov(width: int, height: int, fx: float, fy: float | None = None,
                 cx: float | None = None, cy: float | None = None,
                 frame_id: str = "camera_color_optical_frame") -> "CameraInfo":
        fy = fx if fy is None else fy
        cx = (width - 1) / 2.0 if cx is None else cx
        cy = (height - 1) / 2.0 if cy is None else cy
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return CameraInfo(width, height, K, frame_id)

    def scaled(self, width: int, height: int) -> "CameraInfo":
        """Intrinsics of the same camera resized to width x height."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return CameraInfo(width, height, K, self.frame_id)


@dataclass
class LidarScan:
    """One full LiDAR sweep in the sensor frame.

    ``stamp`` is the sweep's start; ``times_s`` are per-point offsets from the
    stamp (0 .. sweep period), so ``stamp + times_s`` is each point's firing time.
    """

    stamp: float
    points: np.ndarray  # (N, 3) float32/64, metres, in frame_id
    times_s: np.ndarray  # (N,) float, seconds after stamp
    ring: np.ndarray | None = None  # (N,) uint16 beam index (0 = lowest)
    intensity: np.ndarray | None = None  # (N,) float32
    frame_id: str = "velodyne"
    T_world_sensor: np.ndarray | None = None  # ground truth at stamp (simulation / bags with GT only)
    packets: object | None = None  # the sensor's raw packets where it published them (stack.velodyne.VelodynePackets)


@dataclass
class CameraFrame:
    """An RGB image with the depth image aligned to it (either may be missing)."""

    stamp: float
    info: CameraInfo
    rgb: np.ndarray | None = None  # (H, W, 3) uint8
    depth_m: np.ndarray | None = None  # (H, W) float32 metres, 0 = no return
    T_world_camera: np.ndarray | None = None  # ground truth (camera optical frame in world)
    extra: dict = field(default_factory=dict)  # source-specific extras (the sim puts its segmentation here)


@dataclass
class WheelOdometry:
    """Pose of base_link in the wheel-odometry frame ``odom`` and body twist, as the Jackal publishes it."""

    stamp: float
    T_odom_base: np.ndarray  # 4x4
    v: float  # m/s forward
    w: float  # rad/s yaw


@dataclass
class ObjectTruth:
    """Ground-truth state of one object: its cuboid's centroid frame in ``world``."""

    name: str
    cls: str
    T_world_obj: np.ndarray  # 4x4, origin at the cuboid centroid
    dims: np.ndarray  # (3,) cuboid size x y z, metres


@dataclass
class Detection:
    """One DOPE detection in a camera image."""

    cls: str
    stamp: float
    T_cam_obj: np.ndarray  # 4x4 in camera optical frame
    keypoints_px: np.ndarray  # (9, 2) DOPE order, NaN where missing
    peak_scores: np.ndarray  # (9,)
    belief_sum: float  # sum of the final stage's belief tensor for this class (FPR's quantity)
    stages: int = 6
    fpr_pass: bool = True
    extra: dict = field(default_factory=dict)
