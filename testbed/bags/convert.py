"""Conversions between the stack's messages (``stack/messages.py``) and ROS messages.

One :class:`Dialect` per ROS generation carries the type store; everything else
is plain functions from numpy arrays to message objects and back. Times are float
seconds inside and int nanoseconds in the bag.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Literal, Mapping

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from stack.messages import CameraInfo, ObjectTruth, WheelOdometry
from stack.transforms import from_xyz_quat

Format = Literal["ros1", "ros2"]

# --- type stores -------------------------------------------------------------------------

# ROS 1 Noetic's tf2_msgs/TFMessage is missing from rosbags' bundled store; this is its
# definition (md5 94810edda583a504dfda3829e70d7eec, as rosbag records it).
_ROS1_TFMESSAGE = "geometry_msgs/TransformStamped[] transforms"
# velodyne_msgs (the Velodyne driver's raw packets), in each generation's message syntax
VELODYNE_SCAN = "velodyne_msgs/msg/VelodyneScan"
VELODYNE_PACKET = "velodyne_msgs/msg/VelodynePacket"
_VELODYNE_MSGS = {"ros1": ("time stamp\nuint8[1206] data", "Header header\nvelodyne_msgs/VelodynePacket[] packets"),
                  "ros2": ("builtin_interfaces/Time stamp\nuint8[1206] data",
                           "std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets")}

_BASE_DEFAULTS: dict[str, Any] = {"bool": False, "string": ""}
_NUMPY_OF_BASE = {"bool": np.bool_, "int8": np.int8, "uint8": np.uint8, "byte": np.uint8,
                  "char": np.uint8, "int16": np.int16, "uint16": np.uint16, "int32": np.int32,
                  "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
                  "float32": np.float32, "float64": np.float64}


class Dialect:
    """Message construction and (de)serialisation for ROS 1 (Noetic) or ROS 2 (Humble)."""

    def __init__(self, fmt: Format):
        if fmt == "ros1":
            store = get_typestore(Stores.ROS1_NOETIC)
            store.register(get_types_from_msg(_ROS1_TFMESSAGE, "tf2_msgs/msg/TFMessage"))
        elif fmt == "ros2":
            store = get_typestore(Stores.ROS2_HUMBLE)
        else:
            raise ValueError(f"bag format {fmt!r}: expected 'ros1' or 'ros2'")
        packet, scan = _VELODYNE_MSGS[fmt]
        store.register({**get_types_from_msg(packet, VELODYNE_PACKET), **get_types_from_msg(scan, VELODYNE_SCAN)})
        self.format: Format = fmt
        self.typestore = store

    @property
    def ros1(self) -> bool:
        return self.format == "ros1"

    def make(self, msgtype: str, **fields: Any) -> Any:
        """A message of ``msgtype`` with the given fields and defaults (0, '', empty) for the rest.

        Filling defaults keeps one construction path for both generations, whose
        definitions differ (``seq`` in ROS 1 headers, texture fields in ROS 2 markers).
        """
        _, fielddefs = self.typestore.fielddefs[msgtype]
        values = {}
        for name, desc in fielddefs:
            values[name] = fields.pop(name) if name in fields else self._default(desc)
        if fields:
            raise TypeError(f"{msgtype} has no field(s) {sorted(fields)}")
        return self.typestore.types[msgtype](**values)

    def _default(self, desc: tuple) -> Any:
        kind, spec = desc
        if kind == Nodetype.BASE:
            return _BASE_DEFAULTS.get(spec[0], 0)
        if kind == Nodetype.NAME:
            return self.make(spec)
        (sub_kind, sub_spec), length = spec
        if sub_kind == Nodetype.BASE and sub_spec[0] in _NUMPY_OF_BASE:
            n = length if kind == Nodetype.ARRAY else 0
            return np.zeros(n, dtype=_NUMPY_OF_BASE[sub_spec[0]])
        n = length if kind == Nodetype.ARRAY else 0
        return [self._default((sub_kind, sub_spec)) for _ in range(n)]

    def serialize(self, msg: Any, msgtype: str) -> bytes:
        if self.ros1:
            return bytes(self.typestore.serialize_ros1(msg, msgtype))
        return bytes(self.typestore.serialize_cdr(msg, msgtype))

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        if self.ros1:
            return self.typestore.deserialize_ros1(raw, msgtype)
        return self.typestore.deserialize_cdr(raw, msgtype)

    # --- common pieces ---
    def time(self, stamp_ns: int) -> Any:
        sec, nsec = divmod(int(stamp_ns), 10**9)
        return self.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nsec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        return self.make("std_msgs/msg/Header", stamp=self.time(stamp_ns), frame_id=frame_id)

    def pose(self, T: np.ndarray) -> Any:
        T = np.asarray(T, dtype=float)
        xyz, q = T[:3, 3], quat_xyzw(T[:3, :3])
        return self.make(
            "geometry_msgs/msg/Pose",
            position=self.make("geometry_msgs/msg/Point", x=xyz[0], y=xyz[1], z=xyz[2]),
            orientation=self.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))

    def vector3(self, v) -> Any:
        return self.make("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))


@lru_cache(maxsize=None)
def dialect(fmt: Format) -> Dialect:
    return Dialect(fmt)


# --- time -----------------------------------------------------------------------------------

def to_ns(stamp_s: float) -> int:
    """Float seconds to int nanoseconds (the bag's unit); rejects what ROS time cannot hold."""
    if not math.isfinite(stamp_s) or stamp_s < 0:
        raise ValueError(f"stamp {stamp_s!r} s: expected a finite time >= 0")
    return int(round(stamp_s * 1e9))


def time_ns(t: Any) -> int:
    """A ``builtin_interfaces/Time`` (either generation) as int nanoseconds."""
    return int(t.sec) * 10**9 + int(t.nanosec)


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method), for the poses a bag
    is written with (ground truth at the physics rate writes thousands).

    The same rotation as ``stack.transforms.to_xyz_quat`` gives, up to sign and the last bits: that
    one reproduces SciPy's ``Rotation.from_matrix`` bit for bit, this one the bags' own quaternions,
    so recorded bags keep their bytes.
    """
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s
    q = np.array(q, dtype=float)
    return q / np.linalg.norm(q)


def pose_T(pose: Any) -> np.ndarray:
    p, q = pose.position, pose.orientation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=float)
    norm = np.linalg.norm(quat)
    quat = quat / norm if norm > 0 else np.array([0.0, 0.0, 0.0, 1.0])
    return from_xyz_quat([p.x, p.y, p.z], quat)


def transform_T(tf: Any) -> np.ndarray:
    t, q = tf.translation, tf.rotation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=float)
    return from_xyz_quat([t.x, t.y, t.z], quat / np.linalg.norm(quat))


# --- PointCloud2 ----------------------------------------------------------------------------

# sensor_msgs/PointField datatypes
_POINTFIELD_NUMPY = {1: np.int8, 2: np.uint8, 3: np.int16, 4: np.uint16, 5: np.int32,
                     6: np.uint32, 7: np.float32, 8: np.float64}
_NUMPY_POINTFIELD = {np.dtype(v): k for k, v in _POINTFIELD_NUMPY.items()}

# The layout velodyne_pointcloud's PointcloudXYZIRT writes: packed, 22 bytes a point.
VELODYNE_FIELDS = (("x", np.float32), ("y", np.float32), ("z", np.float32),
                   ("intensity", np.float32), ("ring", np.uint16), ("time", np.float32))


def pointcloud2(d: Dialect, stamp_ns: int, frame_id: str, fields: Mapping[str, np.ndarray]) -> Any:
    """An unorganised (height 1), packed, little-endian PointCloud2 with ``fields`` in order.

    Each value is an (N,) array whose dtype is the field's type.
    """
    arrays = {name: np.asarray(v) for name, v in fields.items()}
    sizes = {a.shape[0] for a in arrays.values()}
    if len(sizes) != 1 or any(a.ndim != 1 for a in arrays.values()):
        raise ValueError(f"point fields must be (N,) arrays of one length, got "
                         f"{ {k: a.shape for k, a in arrays.items()} }")
    n = sizes.pop()
    names, formats, offsets, point_fields = [], [], [], []
    offset = 0
    for name, a in arrays.items():
        dtype = np.dtype(a.dtype).newbyteorder("<")
        if dtype.newbyteorder("=") not in _NUMPY_POINTFIELD:
            raise ValueError(f"point field {name!r}: dtype {a.dtype} has no PointField type")
        names.append(name)
        formats.append(dtype)
        offsets.append(offset)
        point_fields.append(d.make("sensor_msgs/msg/PointField", name=name, offset=offset,
                                   datatype=_NUMPY_POINTFIELD[dtype.newbyteorder("=")], count=1))
        offset += dtype.itemsize
    packed = np.empty(n, dtype=np.dtype({"names": names, "formats": formats, "offsets": offsets,
                                         "itemsize": offset}))
    for name, a in arrays.items():
        packed[name] = a
    return d.make("sensor_msgs/msg/PointCloud2", header=d.header(stamp_ns, frame_id), height=1,
                  width=n, fields=point_fields, is_bigendian=False, point_step=offset,
                  row_step=offset * n, data=packed.view(np.uint8).reshape(-1), is_dense=True)


def velodyne_scan(d: Dialect, stamp_ns: int, frame_id: str, data: np.ndarray, stamps_ns: np.ndarray) -> Any:
    """``velodyne_msgs/VelodyneScan``: one sweep's packets (``data`` (P, 1206) uint8, each stamped)."""
    packets = [d.make(VELODYNE_PACKET, stamp=d.time(int(ns)), data=np.ascontiguousarray(row, dtype=np.uint8))
               for row, ns in zip(np.asarray(data), np.asarray(stamps_ns))]
    return d.make(VELODYNE_SCAN, header=d.header(stamp_ns, frame_id), packets=packets)


def velodyne_fields(points: np.ndarray, times_s: np.ndarray, intensity: np.ndarray | None,
                    ring: np.ndarray | None) -> dict[str, np.ndarray]:
    """A scan's arrays in the Velodyne driver's field order and types (time relative to the stamp)."""
    points = np.asarray(points)
    n = points.shape[0]
    values = {
        "x": points[:, 0], "y": points[:, 1], "z": points[:, 2],
        "intensity": np.zeros(n) if intensity is None else intensity,
        "ring": np.zeros(n) if ring is None else ring,
        "time": times_s,
    }
    return {name: np.asarray(values[name]).astype(dtype, copy=False) for name, dtype in VELODYNE_FIELDS}


def cloud_arrays(msg: Any) -> dict[str, np.ndarray]:
    """All fields of a PointCloud2 as (N,) arrays (N = width * height, row padding removed)."""
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _POINTFIELD_NUMPY:
            raise ValueError(f"point field {f.name!r} has unknown datatype {f.datatype}")
        base = np.dtype(_POINTFIELD_NUMPY[f.datatype]).newbyteorder(">" if msg.is_bigendian else "<")
        names.append(f.name)
        formats.append(base if f.count <= 1 else np.dtype((base, (f.count,))))
        offsets.append(f.offset)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": int(msg.point_step)})
    width, height = int(msg.width), int(msg.height)
    data = np.asarray(msg.data, dtype=np.uint8)
    row_bytes = width * int(msg.point_step)
    row_step = int(msg.row_step) or row_bytes
    if data.size < (height - 1) * row_step + row_bytes:
        raise ValueError(f"PointCloud2 data has {data.size} bytes; {height} rows of "
                         f"{row_step} bytes need {height * row_step}")
    if row_step != row_bytes:  # rows padded: drop the padding
        rows = np.lib.stride_tricks.as_strided(data, shape=(height, row_bytes), strides=(row_step, 1))
        data = np.ascontiguousarray(rows).reshape(-1)
    records = np.frombuffer(np.ascontiguousarray(data[: height * row_bytes]), dtype=dtype)
    return {name: records[name] for name in names}


TIME_FIELD_NAMES = ("time", "t", "timestamp")
_SCALES = (1.0, 1e-3, 1e-6, 1e-9)  # seconds, milli, micro, nano
_MAX_SWEEP_S = 1.0  # no spinning LiDAR takes longer for a sweep
_TYPICAL_SWEEP_S = 0.1


@dataclass
class PointTimeEncoding:
    """How a topic's per-point time field maps to seconds: ``value * scale`` (minus the stamp if absolute)."""

    scale: float
    absolute: bool

    def describe(self) -> str:
        unit = {1.0: "s", 1e-3: "ms", 1e-6: "us", 1e-9: "ns"}[self.scale]
        return f"{unit}, {'absolute' if self.absolute else 'relative to the header stamp'}"


def infer_time_encoding(values: np.ndarray, stamp_ns: int) -> tuple[PointTimeEncoding, bool] | None:
    """Guess scale and reference of a per-point time field from one scan.

    Drivers disagree: Velodyne writes float32 seconds after the stamp, Ouster uint32
    nanoseconds after it, Hesai float64 absolute seconds, Livox absolute
    nanoseconds. A sweep lasts at most a second, so exactly one scale puts the
    values within a second of 0 (relative) or of the stamp (absolute); among
    several fits the one whose spread is nearest a 10 Hz sweep wins, and relative
    beats absolute on a tie (they only tie when the stamp is under a second).
    Returns (encoding, certain) or None if no reading fits; ``certain`` is False
    when the scan alone could not tell (constant times, or a stamp near zero).
    """
    v = np.asarray(values)
    integer = np.issubdtype(v.dtype, np.integer)
    vmin, vmax = (int(v.min()), int(v.max())) if integer else (float(v.min()), float(v.max()))
    stamp_s = stamp_ns * 1e-9
    fits = []
    for scale in _SCALES:
        if integer and scale == 1.0:
            continue  # whole seconds per point: no driver does that
        for absolute in (False, True):
            if absolute:
                if integer:
                    ref = int(round(stamp_ns * 1e-9 / scale))
                    lo, hi = (vmin - ref) * scale, (vmax - ref) * scale
                else:
                    lo, hi = vmin * scale - stamp_s, vmax * scale - stamp_s
            else:
                lo, hi = vmin * scale, vmax * scale
            if -_MAX_SWEEP_S <= lo and hi <= _MAX_SWEEP_S:
                span = hi - lo
                badness = abs(math.log10(span / _TYPICAL_SWEEP_S)) if span > 0 else 0.0
                fits.append((badness, absolute, scale))
    if not fits:
        return None
    fits.sort(key=lambda f: (f[0], f[1]))
    best = fits[0]
    ties = [f for f in fits if abs(f[0] - best[0]) < 1e-9]
    certain = (vmax > vmin) and len(ties) == 1 and stamp_s > 2 * _MAX_SWEEP_S
    return PointTimeEncoding(scale=best[2], absolute=best[1]), certain


def times_after_stamp(values: np.ndarray, stamp_ns: int, enc: PointTimeEncoding) -> np.ndarray:
    """Per-point times in float seconds after the stamp."""
    v = np.asarray(values)
    if enc.absolute and np.issubdtype(v.dtype, np.integer):
        ref = int(round(stamp_ns * 1e-9 / enc.scale))  # subtract in integers: ns since 1970 overflow float precision
        return (v.astype(np.int64) - ref).astype(np.float64) * enc.scale
    t = v.astype(np.float64) * enc.scale
    return t - stamp_ns * 1e-9 if enc.absolute else t


# --- images ---------------------------------------------------------------------------------

# encoding -> (numpy dtype, channels)
_IMAGE_LAYOUTS = {
    "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
    "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1),
    "16UC1": (np.uint16, 1), "mono16": (np.uint16, 1), "32FC1": (np.float32, 1),
}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC1")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
DEPTH_MM_MAX = 65535


def image_msg(d: Dialect, stamp_ns: int, frame_id: str, array: np.ndarray, encoding: str) -> Any:
    dtype, channels = _IMAGE_LAYOUTS[encoding]
    a = np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder("<"))
    h, w = a.shape[:2]
    if (a.ndim == 2 and channels != 1) or (a.ndim == 3 and a.shape[2] != channels):
        raise ValueError(f"{encoding} image needs {channels} channel(s), got shape {a.shape}")
    return d.make("sensor_msgs/msg/Image", header=d.header(stamp_ns, frame_id), height=h, width=w,
                  encoding=encoding, is_bigendian=0, step=w * channels * a.itemsize,
                  data=a.view(np.uint8).reshape(-1))


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """Metres to the RealSense 16UC1 millimetres (0 = no return, as is anything out of range)."""
    mm = np.asarray(depth_m, dtype=np.float64) * 1000.0
    valid = np.isfinite(mm) & (mm > 0) & (mm <= DEPTH_MM_MAX)
    out = np.zeros(mm.shape, dtype=np.uint16)
    out[valid] = np.rint(mm[valid]).astype(np.uint16)
    return out


class UnknownEncoding(ValueError, KeyError):
    """An image encoding this converter has no layout for."""

    __str__ = ValueError.__str__


def image_array(msg: Any) -> np.ndarray:
    """Pixels of a sensor_msgs/Image as (H, W) or (H, W, C), row padding removed.

    Raises ``UnknownEncoding`` (a ValueError and a KeyError) for an encoding outside
    ``_IMAGE_LAYOUTS`` and ValueError for short data.
    """
    if msg.encoding not in _IMAGE_LAYOUTS:
        raise UnknownEncoding(f"image encoding {msg.encoding!r}; expected one of {sorted(_IMAGE_LAYOUTS)}")
    dtype, channels = _IMAGE_LAYOUTS[msg.encoding]
    dtype = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < row or data.size < step * h:
        raise ValueError(f"{msg.encoding} image {w}x{h} with step {step} needs {step * h} bytes "
                         f"({row} a row), data has {data.size}")
    rows = data[: step * h].reshape(h, step)[:, :row]
    pixels = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=dtype).reshape(h, w, channels)
    pixels = pixels.astype(pixels.dtype.newbyteorder("="), copy=False)
    return pixels[:, :, 0] if channels == 1 else pixels


def colour_to_rgb(pixels: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB from any of ``COLOUR_ENCODINGS``."""
    if encoding in ("mono8", "8UC1"):
        return np.repeat(pixels[:, :, None], 3, axis=2)
    import cv2

    # OpenCV's channel swaps and alpha drops: the same pixels as NumPy's strided copies, far cheaper
    if encoding == "bgr8":
        return cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB)
    if encoding == "bgra8":
        return cv2.cvtColor(pixels, cv2.COLOR_BGRA2RGB)
    if pixels.shape[2] == 4:
        return cv2.cvtColor(pixels, cv2.COLOR_RGBA2RGB)
    return np.ascontiguousarray(pixels)


def depth_to_metres(pixels: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W) float32 metres, 0 where there is no return."""
    if encoding in ("16UC1", "mono16"):
        return pixels.astype(np.float32) / np.float32(1000.0)
    depth = pixels.astype(np.float32, copy=True)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


# --- camera info, tf, odometry, markers -----------------------------------------------------

def camera_info_msg(d: Dialect, stamp_ns: int, info: CameraInfo, frame_id: str) -> Any:
    K = np.asarray(info.K, dtype=np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    k_names = ("D", "K", "R", "P") if d.ros1 else ("d", "k", "r", "p")
    values = (np.zeros(5), K.reshape(-1), np.eye(3).reshape(-1), P.reshape(-1))
    return d.make("sensor_msgs/msg/CameraInfo", header=d.header(stamp_ns, frame_id),
                  height=int(info.height), width=int(info.width), distortion_model="plumb_bob",
                  **dict(zip(k_names, values)))


def camera_info_from_msg(msg: Any) -> CameraInfo:
    K = np.asarray(getattr(msg, "K", None) if hasattr(msg, "K") else msg.k, dtype=float).reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"camera_info K has no focal length: {K.reshape(-1).tolist()}")
    return CameraInfo(width=int(msg.width), height=int(msg.height), K=K,
                      frame_id=normalize_frame(msg.header.frame_id))


def distortion_of(msg: Any) -> np.ndarray:
    return np.asarray(getattr(msg, "D", None) if hasattr(msg, "D") else msg.d, dtype=float)


def normalize_frame(frame_id: str) -> str:
    """ROS 1 tf allowed a leading slash; tf2 does not."""
    return frame_id.lstrip("/")


def transform_stamped(d: Dialect, stamp_ns: int, parent: str, child: str, T_parent_child: np.ndarray) -> Any:
    T = np.asarray(T_parent_child, dtype=float)
    xyz, q = T[:3, 3], quat_xyzw(T[:3, :3])
    tf = d.make("geometry_msgs/msg/Transform", translation=d.vector3(xyz),
                rotation=d.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))
    return d.make("geometry_msgs/msg/TransformStamped", header=d.header(stamp_ns, parent),
                  child_frame_id=child, transform=tf)


def tf_message(d: Dialect, transforms: list[Any]) -> Any:
    return d.make("tf2_msgs/msg/TFMessage", transforms=transforms)


# Covariance diagonals (x y z roll pitch yaw) in the style of diff_drive_controller configs such
# as the Jackal's: small on the planar axes wheels measure, huge on the rest so an EKF ignores them.
_JACKAL_POSE_COV = (0.001, 0.001, 1e6, 1e6, 1e6, 0.03)
_JACKAL_TWIST_COV = (0.001, 0.001, 0.001, 1e6, 1e6, 0.03)


def odometry_msg(d: Dialect, stamp_ns: int, odom: WheelOdometry, frame_id: str, child: str) -> Any:
    pose = d.make("geometry_msgs/msg/PoseWithCovariance", pose=d.pose(odom.T_odom_base),
                  covariance=np.diag(_JACKAL_POSE_COV).reshape(-1).astype(np.float64))
    twist = d.make("geometry_msgs/msg/Twist", linear=d.vector3((odom.v, 0.0, 0.0)),
                   angular=d.vector3((0.0, 0.0, odom.w)))
    twist_cov = d.make("geometry_msgs/msg/TwistWithCovariance", twist=twist,
                       covariance=np.diag(_JACKAL_TWIST_COV).reshape(-1).astype(np.float64))
    return d.make("nav_msgs/msg/Odometry", header=d.header(stamp_ns, frame_id), child_frame_id=child,
                  pose=pose, twist=twist_cov)


def wheel_odometry_from_msg(msg: Any) -> WheelOdometry:
    return WheelOdometry(stamp=time_ns(msg.header.stamp) * 1e-9, T_odom_base=pose_T(msg.pose.pose),
                         v=float(msg.twist.twist.linear.x), w=float(msg.twist.twist.angular.z))


@dataclass
class Cuboid:
    """An object as a box: what ground truth and the stack's labels share (``T_frame_obj`` in the message's frame)."""

    name: str
    cls: str
    T_frame_obj: np.ndarray  # 4x4, origin at the cuboid centroid
    dims: np.ndarray  # (3,) size along the object's x y z, metres

    @staticmethod
    def from_truth(obj: ObjectTruth) -> "Cuboid":
        return Cuboid(obj.name, obj.cls, np.asarray(obj.T_world_obj, float), np.asarray(obj.dims, float))

    def to_truth(self) -> ObjectTruth:
        return ObjectTruth(self.name, self.cls, self.T_frame_obj, self.dims)


MARKER_CUBE = 1
MARKER_TEXT = 9
MARKER_ADD = 0
MARKER_DELETEALL = 3


def class_colour(cls: str) -> tuple[float, float, float]:
    """A stable colour per class name (same in every run and process)."""
    h = sum((i + 1) * ord(c) for i, c in enumerate(cls)) % 360 / 360.0
    import colorsys

    return colorsys.hsv_to_rgb(h, 0.75, 0.95)


def marker_array(d: Dialect, stamp_ns: int, frame_id: str, cuboids: list[Cuboid]) -> Any:
    """One CUBE marker per object (ns = class, text = name) and a name label above it.

    A DELETEALL first, so RViz drops boxes of an earlier array.
    """
    header = d.header(stamp_ns, frame_id)
    markers = [d.make("visualization_msgs/msg/Marker", header=header, action=MARKER_DELETEALL)]
    for i, c in enumerate(cuboids):
        r, g, b = class_colour(c.cls)
        colour = d.make("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=0.6)
        markers.append(d.make("visualization_msgs/msg/Marker", header=header, ns=c.cls, id=i,
                              type=MARKER_CUBE, action=MARKER_ADD, pose=d.pose(c.T_frame_obj),
                              scale=d.vector3(c.dims), color=colour, text=c.name))
        T_text = np.array(c.T_frame_obj, dtype=float)
        T_text[:3, :3] = np.eye(3)
        T_text[2, 3] += 0.5 * float(np.max(c.dims)) + 0.05
        markers.append(d.make("visualization_msgs/msg/Marker", header=header, ns=f"{c.cls}/name", id=i,
                              type=MARKER_TEXT, action=MARKER_ADD, pose=d.pose(T_text),
                              scale=d.vector3((0.0, 0.0, 0.05)),
                              color=d.make("std_msgs/msg/ColorRGBA", r=1.0, g=1.0, b=1.0, a=1.0),
                              text=c.name))
    return d.make("visualization_msgs/msg/MarkerArray", markers=markers)


def cuboids_from_markers(msg: Any) -> tuple[str, list[Cuboid]]:
    """(frame_id, cuboids) of the CUBE markers in a MarkerArray; other markers are ignored."""
    frame = ""
    out = []
    for m in msg.markers:
        if int(m.type) != MARKER_CUBE or int(m.action) != MARKER_ADD:
            continue
        frame = normalize_frame(m.header.frame_id)
        out.append(Cuboid(name=m.text or f"{m.ns}_{m.id}", cls=m.ns, T_frame_obj=pose_T(m.pose),
                          dims=np.array([m.scale.x, m.scale.y, m.scale.z], dtype=float)))
    return frame, out
