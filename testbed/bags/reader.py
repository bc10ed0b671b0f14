"""Read a ROS 1 or ROS 2 bag (SQLite or MCAP) into the stack's messages.

Works on bags our recorder did not write: topics are found by the usual driver
names or given explicitly, intrinsics come from ``camera_info``, extrinsics from
``/tf_static`` (chained through intermediate frames), per-point LiDAR time may be
called ``time``, ``t`` or ``timestamp`` in any numeric type and unit, and depth
may be 16UC1 millimetres or 32FC1 metres::

    with BagReader("jackal.bag") as bag:
        print(bag.camera_info, bag.T_base_velodyne, bag.T_base_camera)
        for msg in bag.frames():          # LidarScan | CameraFrame | WheelOdometry, by stamp
            ...

Whatever is missing gets an error that names it and lists the bag's topics. A
truncated ROS 1 bag or MCAP file yields the messages of its intact chunks (see
``salvage.py``); nothing here can loop without reading further into the file.
"""
from __future__ import annotations

import heapq
import json
import logging
from bisect import bisect_left
from collections import deque
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import TracebackType
from typing import Any, Callable, Collection, Iterator, Literal

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation, Slerp

from stack.messages import CameraFrame, CameraInfo, LidarScan, ObjectTruth, WheelOdometry
from stack.transforms import interpolate_trajectory, inv

from . import topics as T
from . import images as IM
from .convert import (COLOUR_ENCODINGS, DEPTH_ENCODINGS, TIME_FIELD_NAMES, Cuboid, PointTimeEncoding,
                      camera_info_from_msg, cloud_arrays, colour_to_rgb, cuboids_from_markers,
                      depth_to_metres, distortion_of, image_array, infer_time_encoding,
                      VELODYNE_SCAN, normalize_frame, pose_T, time_ns, times_after_stamp, transform_T,
                      wheel_odometry_from_msg)
from .errors import (BagError, BagReadError, CorruptBagError, MissingExtrinsicError, MissingTopicError,
                     TooManyBadMessagesError,
                     UnsupportedEncodingError)
from .mcap_summary import summary_crc_problem
from .salvage import SalvagedBag, SalvageError

log = logging.getLogger(__name__)

STRAY_STAMP_S = 5.0  # a header stamp this far off its topic's usual offset from the bag time is a stray
MAX_SWEEP_S = 1.0  # a scan's per-point times beyond this are garbage (a spinning LiDAR sweeps in 0.05-0.2 s)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"

Salvage = Literal["auto", "never", "always"]


@dataclass
class GroundTruth:
    """Ground truth carried by a simulated bag: base_link in ``world`` over time, and the objects."""

    base_stamps: np.ndarray  # (N,) seconds, strictly increasing
    T_world_base: np.ndarray  # (N, 4, 4)
    objects: list[ObjectTruth] = field(default_factory=list)

    def T_world_base_at(self, t: float | np.ndarray) -> np.ndarray:
        """SE(3)-interpolated pose(s) at t, clamped to the ends (as ``interpolate_trajectory``)."""
        if len(self.base_stamps) < 2:
            return interpolate_trajectory(self.base_stamps, self.T_world_base, t)
        scalar = np.ndim(t) == 0
        tq = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), self.base_stamps[0], self.base_stamps[-1])
        out = np.tile(np.eye(4), (len(tq), 1, 1))
        out[:, :3, :3] = self._slerp(tq).as_matrix()
        for k in range(3):
            out[:, k, 3] = np.interp(tq, self.base_stamps, self.T_world_base[:, k, 3])
        return out[0] if scalar else out

    @cached_property
    def _slerp(self) -> Slerp:  # built once: a bag's ground truth has thousands of poses
        return Slerp(self.base_stamps, Rotation.from_matrix(self.T_world_base[:, :3, :3]))


# --- sources: the rosbags reader, or the salvage walk --------------------------------------

class _AnyReaderSource:
    """``rosbags.highlevel.AnyReader`` behind the small interface the reader uses."""

    def __init__(self, path: Path):
        default = get_typestore(Stores.ROS2_HUMBLE)  # for old ROS 2 bags without embedded definitions
        self.reader = AnyReader([path], default_typestore=default)
        self.reader.open()
        self.topics = {name: info.msgtype or "" for name, info in self.reader.topics.items()}
        self.counts = {name: info.msgcount for name, info in self.reader.topics.items()}
        self.salvage_summary = ""
        self.skipped_chunks: list[dict] = []

    def messages(self, topics: Collection[str]) -> Iterator[tuple[str, int, str, bytes]]:
        conns = [c for c in self.reader.connections if c.topic in topics]
        if not conns:
            return
        for conn, t_ns, raw in self.reader.messages(connections=conns):
            yield conn.topic, t_ns, conn.msgtype, raw

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self.reader.deserialize(raw, msgtype)

    def close(self) -> None:
        self.reader.close()


class _SalvageSource:
    def __init__(self, paths: list[Path]):
        self.bag = SalvagedBag(paths)
        self.topics = self.bag.topics
        self.counts = self.bag.counts
        self.salvage_summary = self.bag.summary()
        self.skipped_chunks = self.bag.skipped_chunks

    def messages(self, topics: Collection[str]) -> Iterator[tuple[str, int, str, bytes]]:
        return self.bag.messages(topics)

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self.bag.deserialize(raw, msgtype)

    def close(self) -> None:
        pass


def _storage_files(path: Path) -> list[Path]:
    """The storage files of a ROS 2 bag directory (or the file itself)."""
    if path.is_file():
        return [path]
    files = sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3") or p.name.endswith((".mcap.zstd", ".db3.zstd")))
    return files


def _open_source(path: Path, salvage: Salvage) -> _AnyReaderSource | _SalvageSource:
    if not path.exists():
        raise BagReadError(path, "does not exist")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        # a ROS 2 recording that died before writing metadata.yaml: read its storage file directly
        files = [p for p in _storage_files(path) if p.suffix in (".mcap", ".db3")]
        if len(files) != 1:
            raise BagReadError(path, f"a ROS 2 bag directory needs metadata.yaml or exactly one .mcap/.db3 "
                                     f"file; found {[p.name for p in files] or 'none'}")
        log.warning("%s has no metadata.yaml; reading %s directly", path, files[0].name)
        path = files[0]
    if path.is_file() and path.suffix not in (".bag", ".mcap", ".db3"):
        raise BagReadError(path, "not a bag: expected a ROS 1 '.bag' file, a ROS 2 bag directory, "
                                 "or a '.mcap'/'.db3' storage file")
    salvageable = [p for p in _storage_files(path) if p.suffix in (".bag", ".mcap")]
    if salvage == "always":
        return _salvage(path, salvageable, None)
    try:
        for mcap in (p for p in salvageable if p.suffix == ".mcap"):
            problem = summary_crc_problem(mcap)
            if problem is not None:
                raise ValueError(f"{mcap.name}: {problem}")
        return _AnyReaderSource(path)
    except Exception as exc:  # rosbags raises several types for a damaged file; all mean "cannot open"
        if isinstance(exc, PermissionError):
            raise BagReadError(path, f"cannot read: {exc}") from None
        reason = f"{type(exc).__name__}: {exc}"
        if salvage == "never" or not salvageable:
            extra = (" (SQLite storage cannot be recovered once damaged; record with --storage mcap "
                     "to make partial recovery possible)") if any(p.suffix == ".db3" for p in _storage_files(path)) else ""
            raise CorruptBagError(path, f"cannot be opened: {reason}{extra}") from None
        return _salvage(path, salvageable, reason)


def _salvage(path: Path, files: list[Path], reason: str | None) -> _SalvageSource:
    if not files:
        raise CorruptBagError(path, "salvage reads ROS 1 '.bag' and '.mcap' files only")
    why = f"cannot be opened ({reason}); " if reason else ""
    try:
        source = _SalvageSource(files)
    except (SalvageError, OSError, ValueError, KeyError) as exc:
        raise CorruptBagError(path, f"{why}salvage failed: {exc}") from None
    if source.bag.message_count == 0:
        raise CorruptBagError(path, f"{why}no complete message could be recovered: {source.salvage_summary}")
    if reason:
        log.warning("%s %s%s", path, why, source.salvage_summary)
    return source


# --- pairing colour and depth ---------------------------------------------------------------

class _CameraPairer:
    """Pairs each colour image with the depth image nearest in stamp (within ``tolerance``).

    A colour image waits until a depth image at or after its stamp has arrived (so
    the nearest one is known), or until the bag clock is ``wait`` seconds past it.
    """

    def __init__(self, have_rgb: bool, have_depth: bool, tolerance: float, wait: float = 1.0):
        self.have_rgb, self.have_depth = have_rgb, have_depth
        self.tolerance, self.wait = tolerance, wait
        self.pending: deque[tuple[float, np.ndarray]] = deque()
        self.depth_stamps: list[float] = []
        self.depths: list[np.ndarray] = []
        self.depth_used: list[bool] = []
        self.last_rgb = float("-inf")
        self.max_depths = 256
        self.stats = {"paired": 0, "rgb_without_depth": 0, "depth_unused": 0}

    def add_rgb(self, stamp: float, rgb: np.ndarray) -> list[tuple[float, np.ndarray | None, np.ndarray | None]]:
        self.last_rgb = max(self.last_rgb, stamp)
        if not self.have_depth:
            return [(stamp, rgb, None)]
        self.pending.append((stamp, rgb))
        return []

    def add_depth(self, stamp: float, depth: np.ndarray) -> list[tuple[float, np.ndarray | None, np.ndarray | None]]:
        if not self.have_rgb:
            return [(stamp, None, depth)]
        k = bisect_left(self.depth_stamps, stamp)
        self.depth_stamps.insert(k, stamp)
        self.depths.insert(k, depth)
        self.depth_used.insert(k, False)
        return []

    def oldest_pending(self) -> float:
        return self.pending[0][0] if self.pending else float("inf")

    def ready(self, now: float, final: bool = False) -> list[tuple[float, np.ndarray | None, np.ndarray | None]]:
        out: list[tuple[float, np.ndarray | None, np.ndarray | None]] = []
        while self.pending:
            stamp, rgb = self.pending[0]
            later_depth = bool(self.depth_stamps) and self.depth_stamps[-1] >= stamp
            if not (later_depth or final or now > stamp + self.wait):
                break
            self.pending.popleft()
            depth = None
            k = bisect_left(self.depth_stamps, stamp)
            best = min((j for j in (k - 1, k) if 0 <= j < len(self.depth_stamps)),
                       key=lambda j: abs(self.depth_stamps[j] - stamp), default=None)
            if best is not None and abs(self.depth_stamps[best] - stamp) <= self.tolerance:
                depth = self.depths[best]
                self.depth_used[best] = True
                self.stats["paired"] += 1
            else:
                self.stats["rgb_without_depth"] += 1
            out.append((stamp, rgb, depth))
        self._prune(now, final)
        return out

    def _prune(self, now: float, final: bool) -> None:
        """Drop depth images that no pending or later colour image can be nearest to.

        Colour stamps arrive in order, so nothing before the oldest pending (or the
        latest seen) colour stamp minus the tolerance is needed; before any colour
        image has arrived, depth older than ``wait`` of bag time goes. The list is
        capped so a colour stream that never comes cannot fill memory.
        """
        if final:
            horizon = float("inf")
        elif self.last_rgb > float("-inf"):
            horizon = min(self.oldest_pending(), self.last_rgb) - self.tolerance
        else:
            horizon = now - self.wait
        drop = max(bisect_left(self.depth_stamps, horizon), len(self.depth_stamps) - self.max_depths)
        for used in self.depth_used[:drop]:
            self.stats["depth_unused"] += not used
        del self.depth_stamps[:drop], self.depths[:drop], self.depth_used[:drop]


class _Reorder:
    """Releases messages by stamp once nothing earlier can still arrive (bounded memory)."""

    def __init__(self, max_items: int = 512):
        self.heap: list[tuple[float, int, Any]] = []
        self.seq = 0
        self.max_items = max_items

    def push(self, stamp: float, msg: Any) -> None:
        heapq.heappush(self.heap, (stamp, self.seq, msg))
        self.seq += 1

    def release(self, watermark: float) -> Iterator[Any]:
        while self.heap and (self.heap[0][0] <= watermark or len(self.heap) > self.max_items):
            yield heapq.heappop(self.heap)[2]


# --- the reader -----------------------------------------------------------------------------

class BagReader:
    """Sensor messages, calibration and (if present) ground truth of one bag.

    Topic arguments left ``None`` are found by the drivers' usual names, then by
    type (a single candidate). ``T_base_lidar`` / ``T_base_camera`` override
    ``/tf_static``. ``pair_tolerance`` (s) bounds the stamp difference of a
    colour image and the depth image paired with it. ``salvage``: ``auto`` walks
    a ROS 1 or MCAP file that cannot be opened normally and reads its intact
    chunks, ``never`` raises instead, ``always`` walks without trying the index.
    ``ground_truth``: False leaves the ground-truth trajectory unread (``groundtruth`` stays None), for
    a reader that only needs the sensors: reading it passes over every chunk of a simulator's bag.
    ``colour_pixels``: False reads each colour image for its stamp only (the frames are paired and
    stamped as they are with it) and leaves its pixels undecoded and unchecked: every ``CameraFrame``'s
    ``rgb`` is None. For a reader whose consumers use only depth.
    """

    def __init__(self, path: Path | str, lidar_topic: str | None = None, rgb_topic: str | None = None,
                 depth_topic: str | None = None, camera_info_topic: str | None = None,
                 odom_topic: str | None = None, *, base_frame: str = T.BASE,
                 T_base_lidar: np.ndarray | None = None, T_base_camera: np.ndarray | None = None,
                 require_camera: bool = True, pair_tolerance: float = 0.02, salvage: Salvage = "auto",
                 max_bad_messages: int = 10, max_bad_fraction: float = 0.01, ground_truth: bool = True,
                 colour_pixels: bool = True):
        self.path = Path(path)
        self.read_ground_truth = bool(ground_truth)
        self.colour_pixels = bool(colour_pixels)
        self.max_bad_messages = int(max_bad_messages)
        self.max_bad_fraction = float(max_bad_fraction)
        self.bad_messages: dict[str, dict] = {}  # topic -> count, first stamps, first reason (skipped)
        self._good: dict[str, int] = {}
        self._first_bad: dict[str, Exception] = {}
        self._stamp_offsets: dict[str, float] = {}  # topic -> header stamp - bag time of its first message
        self._requested = dict(lidar=lidar_topic, rgb=rgb_topic, depth=depth_topic,
                               camera_info=camera_info_topic, odom=odom_topic)
        self.base_frame = base_frame
        self._T_base_lidar_override = T_base_lidar
        self._T_base_camera_override = T_base_camera
        self.require_camera = require_camera
        self.pair_tolerance = pair_tolerance
        if salvage not in ("auto", "never", "always"):
            raise ValueError(f"salvage={salvage!r}: expected 'auto', 'never' or 'always'")
        self.salvage: Salvage = salvage
        self._source: _AnyReaderSource | _SalvageSource | None = None
        # filled by open()
        self.topics: dict[str, str] = {}
        self.message_counts: dict[str, int] = {}
        self.lidar_topic: str = ""
        self.rgb_topic: str | None = None
        self.depth_topic: str | None = None
        self.camera_info_topic: str | None = None
        self.odom_topic: str | None = None
        self.camera_info: CameraInfo | None = None
        self.lidar_frame = ""
        self.T_base_velodyne = np.eye(4)
        self.T_base_camera: np.ndarray | None = None
        self.groundtruth: GroundTruth | None = None
        self.metadata: dict[str, Any] = {}
        self.time_encoding: PointTimeEncoding | None = None
        self.salvaged = ""  # the salvage summary when the bag was read by walking it
        self.skipped_chunks: list[dict] = []  # damaged chunks passed over (``SalvagedBag.skipped_chunks``)
        self.pairing_stats: dict[str, int] = {}
        self._time_field_warned = False

    # --- lifecycle ---
    def __enter__(self) -> "BagReader":
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def open(self) -> "BagReader":
        self._source = _open_source(self.path, self.salvage)
        try:
            self._read_contents()
        except CorruptBagError as exc:
            self.close()
            if self.salvage != "auto":
                raise
            # the index opened but the data behind it is damaged: read the intact chunks instead
            try:
                self._source = _open_source(self.path, "always")
            except CorruptBagError:
                raise exc from None
            log.warning("%s; reading the intact chunks instead: %s", exc, self._source.salvage_summary)
            try:
                self._read_contents()
            except BaseException:
                self.close()
                raise
        except BaseException:
            self.close()
            raise
        return self

    def _read_contents(self) -> None:
        assert self._source is not None
        self.salvaged = self._source.salvage_summary
        self.skipped_chunks = list(self._source.skipped_chunks)
        self.topics = dict(self._source.topics)
        self.message_counts = dict(self._source.counts)
        self._resolve_topics()
        self._read_calibration()
        if self.read_ground_truth:
            self._read_ground_truth()
        self._read_metadata()

    def close(self) -> None:
        source, self._source = self._source, None
        if source is not None:
            source.close()

    # --- iteration ---
    def frames(self, lidar: bool = True, camera: bool = True, odometry: bool = True
               ) -> Iterator[LidarScan | CameraFrame | WheelOdometry]:
        """Sensor messages in stamp order (colour and depth merged into one CameraFrame)."""
        streams = {}
        if lidar:
            streams[self.lidar_topic] = "lidar"
        if camera and self.rgb_topic:
            streams[self.rgb_topic] = "rgb"
        if camera and self.depth_topic:
            streams[self.depth_topic] = "depth"
        if odometry and self.odom_topic:
            streams[self.odom_topic] = "odom"
        pairer = _CameraPairer("rgb" in streams.values(), "depth" in streams.values(), self.pair_tolerance)
        out = _Reorder()
        now = float("-inf")
        for topic, t_ns, msg in self._messages(streams):
            kind = streams[topic]
            now = t_ns * 1e-9
            try:
                if kind == "lidar":
                    scan = self._scan(msg, t_ns)
                    self._check_stamp(topic, scan.stamp, now)
                    out.push(scan.stamp, scan)
                elif kind == "odom":
                    odom = wheel_odometry_from_msg(msg)
                    if odom.stamp == 0.0:
                        odom.stamp = now
                    self._check_stamp(topic, odom.stamp, now)
                    out.push(odom.stamp, odom)
                elif kind == "rgb":
                    stamp = self._check_stamp(topic, self._stamp(msg, t_ns), now)
                    for item in pairer.add_rgb(stamp, self._rgb(msg) if self.colour_pixels else None):
                        out.push(item[0], self._camera_frame(*item))
                else:
                    stamp = self._check_stamp(topic, self._stamp(msg, t_ns), now)
                    for item in pairer.add_depth(stamp, self._depth(msg)):
                        out.push(item[0], self._camera_frame(*item))
            except (UnsupportedEncodingError, ValueError) as exc:
                self._skip(topic, now, exc)  # one bad message is skipped, counted and named
                continue
            self._good[topic] = self._good.get(topic, 0) + 1
            for item in pairer.ready(now):
                out.push(item[0], self._camera_frame(*item))
            yield from out.release(min(pairer.oldest_pending(), now - 0.5))
        for item in pairer.ready(now, final=True):
            out.push(item[0], self._camera_frame(*item))
        yield from out.release(float("inf"))
        for topic, exc in self._first_bad.items():
            if not self._good.get(topic):  # every message of the topic was bad: nothing usable, say why
                raise exc
        self.pairing_stats = dict(pairer.stats)

    def scans(self) -> Iterator[LidarScan]:
        """LiDAR scans only (the odometry pass)."""
        for msg in self.frames(lidar=True, camera=False, odometry=False):
            assert isinstance(msg, LidarScan)
            yield msg

    def camera_frames(self) -> Iterator[CameraFrame]:
        """Camera frames only (the detection pass)."""
        for msg in self.frames(lidar=False, camera=True, odometry=False):
            assert isinstance(msg, CameraFrame)
            yield msg

    def wheel_odometry(self) -> Iterator[WheelOdometry]:
        for msg in self.frames(lidar=False, camera=False, odometry=True):
            assert isinstance(msg, WheelOdometry)
            yield msg

    def messages(self, topics: Collection[str]) -> Iterator[tuple[str, float, Any]]:
        """(topic, bag time in s, deserialised ROS message) for any topics, in bag-time order."""
        missing = [t for t in topics if t not in self.topics]
        if missing:
            raise MissingTopicError(self.path, "requested", ", ".join(missing), self.topics)
        for topic, t_ns, msg in self._messages(topics):
            yield topic, t_ns * 1e-9, msg

    # --- results and extras ---
    def labels(self, topic: str = T.LABELS) -> tuple[str, list[Cuboid]] | None:
        """(frame, cuboids) of the last MarkerArray on ``topic``, or None if the bag has none."""
        msg = self._last(topic, MARKER_ARRAY)
        return None if msg is None else cuboids_from_markers(msg)

    def map_points(self, topic: str = T.MAP) -> np.ndarray | None:
        """(N, 3) points of the last PointCloud2 on ``topic`` (the stack's map), or None."""
        msg = self._last(topic, POINTCLOUD2)
        if msg is None:
            return None
        arrays = cloud_arrays(msg)
        return np.stack([arrays["x"], arrays["y"], arrays["z"]], axis=1)

    def describe(self) -> str:
        lines = [f"{self.path}: lidar {self.lidar_topic} (frame {self.lidar_frame}), "
                 f"rgb {self.rgb_topic}, depth {self.depth_topic}, camera_info {self.camera_info_topic}, "
                 f"odometry {self.odom_topic}, ground truth {'yes' if self.groundtruth else 'no'}"]
        if self.salvaged:
            lines.append(f"salvaged: {self.salvaged}")
        return "\n".join(lines)

    # --- opening steps ---
    def _resolve_topics(self) -> None:
        req = self._requested
        self.lidar_topic = self._pick("lidar", req["lidar"], (POINTCLOUD2, VELODYNE_SCAN), T.LIDAR_CANDIDATES,
                                      lambda name: name not in T.RESULT_TOPICS, required=True) or ""
        images = (IMAGE, COMPRESSED_IMAGE)
        self.rgb_topic = self._pick("rgb", req["rgb"], images, T.RGB_CANDIDATES,
                                    lambda n: ("color" in n or "rgb" in n) and "depth" not in n)
        self.depth_topic = self._pick("depth", req["depth"], images, T.DEPTH_CANDIDATES,
                                      lambda n: "depth" in n and "aligned" in n)
        if self.require_camera and not (self.rgb_topic or self.depth_topic):
            raise MissingTopicError(self.path, "camera image", f"{T.RGB} or {T.DEPTH} (sensor_msgs/Image)",
                                    self.topics, "pass --rgb-topic and/or --depth-topic, or --odometry-only for the "
                                    "trajectory alone")
        if self.rgb_topic or self.depth_topic:
            candidates = [t for t in (self._sibling_info(self.rgb_topic), T.RGB_INFO,
                                      self._sibling_info(self.depth_topic), T.DEPTH_INFO) if t]
            self.camera_info_topic = self._pick("camera_info", req["camera_info"], (CAMERA_INFO,), candidates,
                                                lambda n: False, required=True)
        self.odom_topic = self._pick("odometry", req["odom"], (ODOMETRY,), T.ODOM_CANDIDATES, lambda n: False)

    def _pick(self, what: str, requested: str | None, types: tuple[str, ...], names: tuple[str, ...] | list[str],
              accept: Callable[[str], bool], required: bool = False) -> str | None:
        expected = " or ".join(types)
        if requested is not None:
            if requested not in self.topics:
                raise MissingTopicError(self.path, what, f"{requested!r} ({expected})", self.topics)
            if self.topics[requested] not in types:
                raise MissingTopicError(self.path, what, f"{requested!r} to carry {expected}", self.topics,
                                        f"it carries {self.topics[requested]}")
            return requested
        for name in names:
            if self.topics.get(name) in types:
                return name
        by_type = [n for n, ty in self.topics.items() if ty in types and accept(n)]
        if len(by_type) == 1:
            return by_type[0]
        if required:
            option = {"camera_info": "--camera-info-topic"}.get(what, f"--{what}-topic")
            hint = (f"several candidates ({', '.join(sorted(by_type))}): pass {option}" if by_type
                    else f"pass {option} if it has another name")
            raise MissingTopicError(self.path, what, f"{names[0]} or another {expected} topic", self.topics, hint)
        return None

    @staticmethod
    def _sibling_info(image_topic: str | None) -> str | None:
        if not image_topic:
            return None
        base = image_topic[: -len("/compressed")] if image_topic.endswith("/compressed") else image_topic
        return base.rsplit("/", 1)[0] + "/camera_info"

    def _read_calibration(self) -> None:
        first_scan = self._first(self.lidar_topic)
        if first_scan is None:
            raise MissingTopicError(self.path, "lidar", f"messages on {self.lidar_topic}", self.topics,
                                    "the topic is listed but has no (complete) message")
        self.lidar_frame = normalize_frame(first_scan.header.frame_id)
        if self.camera_info_topic:
            msg = self._first(self.camera_info_topic)
            if msg is None:
                raise MissingTopicError(self.path, "camera_info", f"messages on {self.camera_info_topic}",
                                        self.topics, "the topic is listed but has no (complete) message")
            try:
                self.camera_info = camera_info_from_msg(msg)
            except ValueError as exc:
                raise UnsupportedEncodingError(self.path, self.camera_info_topic, str(exc),
                                               "a calibrated K (fx, fy > 0)") from None
            if np.any(np.abs(distortion_of(msg)) > 1e-6):
                log.warning("%s: %s has distortion %s; images are used as if rectified", self.path,
                            self.camera_info_topic, np.round(distortion_of(msg), 4).tolist())
        tree = self._static_tree()
        if self._T_base_lidar_override is not None:
            self.T_base_velodyne = np.asarray(self._T_base_lidar_override, dtype=float)
        else:
            self.T_base_velodyne = self._extrinsic(tree, self.lidar_frame, "T_base_lidar (--T-base-lidar)")
        if self.camera_info is not None:
            if self._T_base_camera_override is not None:
                self.T_base_camera = np.asarray(self._T_base_camera_override, dtype=float)
            else:
                self.T_base_camera = self._extrinsic(tree, self.camera_info.frame_id,
                                                     "T_base_camera (--T-base-camera)")

    def _static_tree(self) -> dict[str, dict[str, np.ndarray]]:
        """frame -> {neighbour: T_frame_neighbour} from every /tf_static message (both directions)."""
        tree: dict[str, dict[str, np.ndarray]] = {}
        if self.topics.get(T.TF_STATIC) != TFMESSAGE:
            return tree
        for _, _, msg in self._messages([T.TF_STATIC]):
            for tf in msg.transforms:
                parent, child = normalize_frame(tf.header.frame_id), normalize_frame(tf.child_frame_id)
                T_parent_child = transform_T(tf.transform)
                tree.setdefault(parent, {})[child] = T_parent_child
                tree.setdefault(child, {})[parent] = inv(T_parent_child)
        return tree

    def _extrinsic(self, tree: dict[str, dict[str, np.ndarray]], frame: str, option: str) -> np.ndarray:
        """T_base_frame by breadth-first search over the static tree."""
        if frame == self.base_frame:
            return np.eye(4)
        found = {self.base_frame: np.eye(4)}
        queue = deque([self.base_frame])
        while queue:
            a = queue.popleft()
            for b, T_a_b in tree.get(a, {}).items():
                if b not in found:
                    found[b] = found[a] @ T_a_b
                    if b == frame:
                        return found[b]
                    queue.append(b)
        raise MissingExtrinsicError(self.path, self.base_frame, frame, list(tree), self.topics, option)

    def _read_ground_truth(self) -> None:
        if self.topics.get(T.GT_BASE_POSE) != POSE_STAMPED:
            return
        stamps, poses = [], []
        for _, t_ns, msg in self._messages([T.GT_BASE_POSE]):
            stamps.append(self._stamp(msg, t_ns))
            poses.append(pose_T(msg.pose))
        if not stamps:
            return
        # one pose per stamp (the recorder may write one for each sensor message at that stamp)
        stamps_arr = np.asarray(stamps)
        order = np.argsort(stamps_arr, kind="stable")
        _, first = np.unique(stamps_arr[order][::-1], return_index=True)
        order = order[::-1][first]  # the last pose written at each stamp, in stamp order
        objects: list[ObjectTruth] = []
        last = self._last(T.GT_OBJECTS, MARKER_ARRAY)
        if last is not None:
            objects = [c.to_truth() for c in cuboids_from_markers(last)[1]]
        self.groundtruth = GroundTruth(stamps_arr[order], np.asarray(poses)[order], objects)

    def _read_metadata(self) -> None:
        msg = self._last(T.METADATA, "std_msgs/msg/String")
        if msg is not None:
            try:
                self.metadata = json.loads(msg.data)
            except json.JSONDecodeError as exc:
                log.warning("%s: %s is not JSON (%s); ignored", self.path, T.METADATA, exc)

    # --- conversions ---
    def _stamp(self, msg: Any, t_ns: int) -> float:
        """Header stamp in seconds; the bag time where the driver left the stamp at zero."""
        ns = time_ns(msg.header.stamp)
        return (ns if ns > 0 else t_ns) * 1e-9

    def _scan(self, msg: Any, t_ns: int) -> LidarScan:
        topic = self.lidar_topic
        if hasattr(msg, "packets"):
            return self._packet_scan(msg, t_ns)
        try:
            arrays = cloud_arrays(msg)
        except ValueError as exc:
            raise UnsupportedEncodingError(self.path, topic, str(exc), "a well-formed PointCloud2") from None
        if not {"x", "y", "z"} <= arrays.keys():
            raise UnsupportedEncodingError(self.path, topic, f"point fields {sorted(arrays)}",
                                           "fields x, y, z", self.topics)
        points = np.stack([arrays["x"], arrays["y"], arrays["z"]], axis=1).astype(np.float32, copy=False)
        x, y, z = points.T  # column by column: numpy's row-wise all/any over 3 values is several times slower
        valid = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
        valid &= (x != 0) | (y != 0) | (z != 0)  # organised clouds mark no-returns
        if valid.all():
            valid = slice(None)  # every point: no copies
        stamp_ns = time_ns(msg.header.stamp) or t_ns
        time_name = next((n for n in TIME_FIELD_NAMES if n in arrays), None)
        if time_name is None:
            if not self._time_field_warned:
                log.warning("%s: %s has no per-point time field (%s); scans are not deskewed", self.path,
                            topic, "/".join(TIME_FIELD_NAMES))
                self._time_field_warned = True
            times = np.zeros(len(points[valid]))
        else:
            raw_times = arrays[time_name][valid]
            enc = self.time_encoding
            if enc is None and raw_times.size:
                guess = infer_time_encoding(raw_times, stamp_ns)
                if guess is None:
                    raise UnsupportedEncodingError(
                        self.path, topic,
                        f"point field {time_name!r} ({raw_times.dtype}) spans {raw_times.min()}..{raw_times.max()} "
                        f"with the stamp at {stamp_ns} ns, which fits no unit",
                        "seconds, ms, us or ns within 1 s of 0 (relative) or of the stamp (absolute)")
                enc, certain = guess
                if certain:
                    self.time_encoding = enc
                    log.info("%s: %s point field %r read as %s", self.path, topic, time_name, enc.describe())
            times = times_after_stamp(raw_times, stamp_ns, enc) if raw_times.size else np.zeros(0)
        stamp = stamp_ns * 1e-9
        if times.size and times.min() < 0:  # stamped at the sweep's end (or middle): restamp at its start
            t0 = float(times.min())
            stamp += t0
            times = times - t0
        if times.size and not (np.all(np.isfinite(times)) and float(times.max()) <= MAX_SWEEP_S):
            raise UnsupportedEncodingError(self.path, topic, f"point field {time_name!r}: per-point times span "
                                           f"{float(np.nanmax(times)) if np.isfinite(times).any() else 'nan'} s",
                                           f"a sweep of at most {MAX_SWEEP_S} s")
        ring = arrays["ring"][valid].astype(np.uint16) if "ring" in arrays else None
        intensity = arrays["intensity"][valid].astype(np.float32) if "intensity" in arrays else None
        scan = LidarScan(stamp=stamp, points=points[valid], times_s=times, ring=ring, intensity=intensity,
                         frame_id=self.lidar_frame or normalize_frame(msg.header.frame_id))
        if self.groundtruth is not None:
            scan.T_world_sensor = self.groundtruth.T_world_base_at(stamp) @ self.T_base_velodyne
        return scan

    def _packet_scan(self, msg: Any, t_ns: int) -> LidarScan:
        """A ``velodyne_msgs/VelodyneScan`` decoded as velodyne_pointcloud decodes a VLP-32C's packets
        (``stack.velodyne``), restamped at its first return where the driver stamped the sweep's end."""
        from stack.velodyne import PACKET_BYTES, PacketError, VelodynePackets, decode_sweep

        topic = self.lidar_topic
        try:
            rows = [np.frombuffer(np.asarray(pk.data, dtype=np.uint8).tobytes(), dtype=np.uint8)
                    for pk in msg.packets]
            if any(r.size != PACKET_BYTES for r in rows):
                raise PacketError(f"a packet of {next(r.size for r in rows if r.size != PACKET_BYTES)} bytes: "
                                  f"expected {PACKET_BYTES}")
            data = np.stack(rows) if rows else np.zeros((0, PACKET_BYTES), dtype=np.uint8)
            stamps = np.array([time_ns(pk.stamp) for pk in msg.packets], dtype=np.int64)
            packets = VelodynePackets(data, stamps)
            stamp_ns = time_ns(msg.header.stamp) or t_ns
            scan = decode_sweep(packets, stamp_ns, frame_id=self.lidar_frame or normalize_frame(msg.header.frame_id))
        except PacketError as exc:
            raise UnsupportedEncodingError(self.path, topic, str(exc), "VLP-32C data packets") from None
        if scan.times_s.size and not (np.all(np.isfinite(scan.times_s))
                                      and float(np.ptp(scan.times_s)) <= MAX_SWEEP_S):
            raise UnsupportedEncodingError(self.path, topic, f"packet stamps spanning {float(np.ptp(scan.times_s))} s",
                                           f"a sweep of at most {MAX_SWEEP_S} s")
        if scan.times_s.size and scan.times_s.min() < 0:  # stamped at the sweep's end: restamp at its start
            t0 = float(scan.times_s.min())
            scan.stamp += t0
            scan.times_s = scan.times_s - t0
        scan.packets = packets
        if self.groundtruth is not None:
            scan.T_world_sensor = self.groundtruth.T_world_base_at(scan.stamp) @ self.T_base_velodyne
        return scan

    def _rgb(self, msg: Any) -> np.ndarray:
        topic = self.rgb_topic or ""
        if not hasattr(msg, "encoding"):  # CompressedImage
            try:
                rgb = IM.decode_rgb(msg)
            except ValueError as exc:
                raise UnsupportedEncodingError(self.path, topic, str(exc), "jpeg or png") from None
        else:
            if msg.encoding not in COLOUR_ENCODINGS:
                raise UnsupportedEncodingError(self.path, topic, f"image encoding {msg.encoding!r}",
                                               f"one of {', '.join(COLOUR_ENCODINGS)}", self.topics)
            rgb = colour_to_rgb(self._pixels(msg, topic), msg.encoding)
        self._check_size(rgb.shape, topic)
        return rgb

    def _depth(self, msg: Any) -> np.ndarray:
        topic = self.depth_topic or ""
        if not hasattr(msg, "encoding"):  # CompressedImage: image_transport's compressedDepth
            try:
                depth = depth_to_metres(IM.decode_depth_mm(msg), "16UC1")
            except ValueError as exc:
                raise UnsupportedEncodingError(self.path, topic, str(exc), "16UC1; compressedDepth png") from None
            self._check_size(depth.shape, topic)
            return depth
        if msg.encoding not in DEPTH_ENCODINGS:
            raise UnsupportedEncodingError(self.path, topic, f"depth encoding {msg.encoding!r}",
                                           "16UC1 (millimetres) or 32FC1 (metres)", self.topics)
        depth = depth_to_metres(self._pixels(msg, topic), msg.encoding)
        self._check_size(depth.shape, topic)
        return depth

    def _pixels(self, msg: Any, topic: str) -> np.ndarray:
        try:
            return image_array(msg)
        except ValueError as exc:
            raise UnsupportedEncodingError(self.path, topic, str(exc), "a well-formed image") from None

    def _check_size(self, shape: tuple[int, ...], topic: str) -> None:
        info = self.camera_info
        assert info is not None
        if (shape[0], shape[1]) != (info.height, info.width):
            raise UnsupportedEncodingError(
                self.path, topic, f"image {shape[1]}x{shape[0]}",
                f"{info.width}x{info.height} as {self.camera_info_topic} says (depth must be aligned to colour)")

    def _camera_frame(self, stamp: float, rgb: np.ndarray | None, depth: np.ndarray | None) -> CameraFrame:
        assert self.camera_info is not None
        return CameraFrame(stamp=stamp, info=self.camera_info, rgb=rgb, depth_m=depth,
                           T_world_camera=self.true_camera_pose(stamp))

    def true_camera_pose(self, stamp: float) -> np.ndarray | None:
        """The camera's true pose at ``stamp`` (``camera_color_optical_frame`` in ``world``) from the
        bag's ground truth; None without it."""
        if self.groundtruth is None or self.T_base_camera is None:
            return None
        return self.groundtruth.T_world_base_at(stamp) @ self.T_base_camera

    # --- bad messages ---
    def _skip(self, topic: str, t: float, exc: Exception) -> None:
        """Count a message that cannot be converted; beyond ``max_bad_messages`` (or the fraction
        ``max_bad_fraction`` of a topic's messages, whichever is larger) stop with InputDataError."""
        text = exc.message if isinstance(exc, BagError) else f"{type(exc).__name__}: {exc}"
        entry = self.bad_messages.setdefault(topic, {"count": 0, "first_stamps_s": [], "reason": text})
        entry["count"] += 1
        self._first_bad.setdefault(topic, exc)
        if len(entry["first_stamps_s"]) < 5:
            entry["first_stamps_s"].append(round(t, 9))
        log.warning("%s: skipped a message on %s at %.3f s (%s)", self.path, topic, t, text.splitlines()[0])
        limit = max(self.max_bad_messages, int(self.max_bad_fraction * self.message_counts.get(topic, 0)))
        if entry["count"] > limit:
            if not self._good.get(topic):  # not one good message: the topic's layout is wrong, say so
                raise exc
            raise TooManyBadMessagesError(self.path, f"{entry['count']} bad messages on {topic} (more than {limit}; "
                                 f"the first: {text.splitlines()[0]}); raise --max-bad-messages to skip more")

    def _check_stamp(self, topic: str, stamp: float, bag_time: float) -> float:
        """A header stamp whose offset from the bag's record time differs from the topic's usual
        offset by more than ``STRAY_STAMP_S`` is a stray (a clock jump, a garbage stamp): the message
        is skipped and reported, so it cannot stretch the trajectory or the replayed span."""
        offset = stamp - bag_time
        ref = self._stamp_offsets.setdefault(topic, offset)  # the first message's offset
        if abs(offset - ref) > STRAY_STAMP_S:
            raise UnsupportedEncodingError(self.path, topic, f"header stamp {stamp:.3f} s is {offset - ref:+.1f} s off "
                                           "the topic's other stamps", f"stamps within {STRAY_STAMP_S} s of them")
        return stamp

    def bad_message_summary(self) -> dict[str, dict]:
        """Per topic: how many messages were skipped, the first stamps and the first reason."""
        return {t: dict(v) for t, v in sorted(self.bad_messages.items())}

    # --- message access ---
    def _messages(self, topics: Collection[str]) -> Iterator[tuple[str, int, Any]]:
        source = self._source
        if source is None:
            raise BagReadError(self.path, "reader is not open (use it in a with block)")
        last_t = None
        at_last = 0  # messages yielded at last_t (a resumed walk skips them)
        try:
            for topic, t_ns, msgtype, raw in source.messages(topics):
                msg = source.deserialize(raw, msgtype)
                at_last = at_last + 1 if t_ns == last_t else 1
                last_t = t_ns
                yield topic, t_ns, msg
        except BagError:
            raise
        except Exception as exc:  # any failure inside the third-party parser means a damaged file
            where = f"after the message at {last_t * 1e-9:.3f} s" if last_t is not None else "at its first message"
            reason = f"damaged {where} ({type(exc).__name__}: {exc})"
            if self.salvage != "auto" or not isinstance(source, _AnyReaderSource) or self._source is not source:
                hint = "" if self.salvage == "always" else "; BagReader(..., salvage='always') reads the intact chunks"
                raise CorruptBagError(self.path, f"{reason}{hint}") from None
        else:
            return
        # a chunk behind the index is damaged (bad CRC, undecodable): go on from the intact chunks
        try:
            walked = _open_source(self.path, "always")
        except CorruptBagError:
            raise CorruptBagError(self.path, reason) from None
        source.close()
        self._source = walked
        self.salvaged = walked.salvage_summary
        self.skipped_chunks = list(walked.skipped_chunks)
        log.warning("%s: %s; reading the intact chunks instead: %s", self.path, reason, walked.salvage_summary)
        seen = 0
        for topic, t_ns, msg in self._messages(topics):
            if last_t is not None and (t_ns < last_t or (t_ns == last_t and seen < at_last)):
                seen += t_ns == last_t
                continue
            yield topic, t_ns, msg

    def _first(self, topic: str) -> Any | None:
        gen = self._messages([topic])
        try:
            return next(gen)[2]
        except StopIteration:
            return None
        finally:
            gen.close()

    def _last(self, topic: str, msgtype: str) -> Any | None:
        if self.topics.get(topic) != msgtype:
            return None
        last = None
        for _, _, msg in self._messages([topic]):
            last = msg
        return last

