"""The DOPESLAM pipeline: sensor messages in time order in, an object map and a trajectory out.

    LidarScan        -> odometry (T_map_base per sweep)
    CameraFrame      -> detector (DOPE + FPR) -> waits for a pose -> fusion -> object store
    WheelOdometry    -> kept as a second trajectory (for comparison), and given to an odometry
                        that uses it (``on_wheel_odometry``)
    finish()         -> the last images fused, the store's floor set from the odometry, labels published

One rule for the images: an image's detections are fused once the odometry has a pose *after* the
image's stamp (the next registered sweep), so the robot pose at the image is interpolated between
two sweeps, never extrapolated from a stale one. At ``finish`` the images still waiting are fused if
the odometry gives a pose at their stamp (its bounded extrapolation past the last sweep), else
dropped and counted in ``unposed``. Images before the first sweep are fused at the first sweep with
whatever pose the odometry gives there (the LiDAR odometry: the first pose, within its bounded
extrapolation), else dropped.

Where the messages come from (a simulator, a rosbag, a robot) is not this module's business, nor is
scoring: ``on_image`` returns the image's detections so a harness can score them against its truth,
and ``on_fused_image`` hands each image over once it is fused (for a harness that labels on its own).
The components are the :mod:`stack.interfaces` protocols, so other people's odometry, detector,
labelling policy or loop closer plug in without changes here.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from stack.evidence import carry_views, count_views
from stack.fusion import fuse
from stack.interfaces import Detector, LoopCloser, Odometry, check_pose, check_trajectory, detect
from stack.keyframes import KeyframeSettings, keyframe_gate
from stack.lidar_slam import WheelOdometryTrack
from stack.messages import CameraFrame, Detection, LidarScan, WheelOdometry
from stack.object_store import ObjectStore, Observation
from stack.retire import RetireConfig, Retirement, carry_over
from stack.transforms import transform_points, voxel_thin

MAP_EVERY = 5  # every 5th registered sweep goes into the LiDAR map (a picture, not used for labels) ...
MAP_POINT_STRIDE = 4  # ... with every 4th of its points
MAP_POINT_LIMIT = 500_000  # past this many points the LiDAR map is thinned to one point per voxel (long runs) ...
MAP_VOXEL_M = 0.05  # ... of this size, so its memory follows the space explored, not the time


@dataclass
class PipelineResult:
    """What :meth:`DopeSlam.finish` returns.

    ``T_map_base``: the trajectory at ``stamps`` (loop-corrected when the pipeline has a loop
    closer; the odometry's own is ``T_map_base_odometry``). ``map_points``: the LiDAR map in ``map``,
    one (N, 3) array per kept sweep. ``observations``: every fused detection in ``map`` (only with
    ``keep_observations``). ``unposed``: detections dropped because no pose was known at their stamp.
    """

    store: ObjectStore
    stamps: np.ndarray
    T_map_base: np.ndarray
    T_map_base_odometry: np.ndarray
    wheel_stamps: np.ndarray
    T_odom_base: np.ndarray  # wheel odometry, re-expressed with odom = base_link at its first message
    map_points: list[np.ndarray] = field(default_factory=list)
    observations: list[Observation] = field(default_factory=list)
    unposed: int = 0


@dataclass
class FusedImage:
    """One detected image once the pipeline fused it (see ``DopeSlam(on_fused_image=...)``).

    ``index``: the image's number among the detected ones (0, 1, ...). ``T_map_base``: the robot pose
    at ``stamp``; None when the odometry had none. ``observations``: per detection (same order), the
    detection in ``map``, or None where the odometry had no pose at its stamp (dropped, ``unposed``).
    """

    index: int
    stamp: float
    T_map_base: np.ndarray | None
    detections: list[Detection]
    observations: list[Observation | None]


@dataclass
class _Waiting:
    index: int
    stamp: float
    detections: list[Detection]
    frame: CameraFrame | None = None  # kept for the views and the retirement check (its pose, intrinsics, depth)


class DopeSlam:
    """Odometry + detector + fusion + object store, fed one message at a time.

    ``odometry``, ``detector``: see :mod:`stack.interfaces` (``detector`` None: no detector runs, only
    images given their detections do; e.g. odometry and loop closure alone). ``T_base_cam``: the
    camera's mounting (``camera_color_optical_frame`` in ``base_link``). ``dims``: cuboid size per
    class, for the store (every class the detector reports must be there). ``policy``: a labelling
    policy's registered name (:data:`stack.object_store.POLICIES`). ``loop_closer``: optional, see
    :class:`stack.interfaces.LoopCloser`. ``detect_every``: run the detector on every n-th image
    only. ``keep_observations``: keep every fused observation in the result. ``on_fused_image``:
    called with each :class:`FusedImage` when it is fused, in image order. ``map_objects``: False
    keeps the fused observations out of the object store (a harness that labels on its own).
    ``retire``: retire map objects whose place the depth images show empty (:mod:`stack.retire`);
    None: never. ``count_views``: count, per map object, the detected images that showed its place
    (:func:`stack.evidence.count_views`; the evidence gate's detection rate). ``keyframes``: a
    :class:`stack.keyframes.KeyframeSettings`: the detector runs only on images the robot has moved
    or turned enough for since the last detected one (by its wheel odometry), or after a while.
    """

    def __init__(self, odometry: Odometry, detector: Detector | None, T_base_cam: np.ndarray,
                 dims: Mapping[str, Sequence[float]], policy: str = "robust-mean",
                 loop_closer: LoopCloser | None = None, detect_every: int = 1, keep_observations: bool = False,
                 on_fused_image: Callable[[FusedImage], None] | None = None, map_objects: bool = True,
                 retire: RetireConfig | None = None, count_views: bool = True,
                 keyframes: KeyframeSettings | None = None):
        if detector is not None and not isinstance(detector, Detector):
            raise TypeError(f"detector {type(detector).__name__} has no detect(frame) method")
        if not isinstance(odometry, Odometry):
            raise TypeError(f"odometry {type(odometry).__name__} lacks process(scan), pose_at(t) or trajectory()")
        if detect_every < 1:
            raise ValueError(f"detect_every must be >= 1, got {detect_every}")
        self.odometry = odometry
        self.detector = detector
        self.T_base_cam = np.asarray(T_base_cam, dtype=float)
        self.dims = dict(dims)
        self.policy = policy
        self.loop_closer = loop_closer
        self.detect_every = int(detect_every)
        self.keyframes = keyframe_gate(keyframes)
        self.keep_observations = keep_observations
        self.on_fused_image = on_fused_image
        self.map_objects = map_objects
        self.retirement = Retirement(retire) if retire is not None else None
        self.count_views = bool(count_views)
        self.store = ObjectStore(dims=self.dims, policy=policy)
        self.wheel = WheelOdometryTrack()
        self._odometry_wheel = getattr(odometry, "on_wheel_odometry", None)
        self.timing = {"odometry": 0.0, "detection": 0.0, "fusion": 0.0}  # seconds spent in each
        self.images = 0  # images received
        self.detected_images = 0  # images detected (by the detector, or given their detections)
        self.unposed = 0
        self._pending: list[_Waiting] = []  # detected images waiting for a pose after their stamp
        self._observations: list[Observation] = []
        self._map_points: list[np.ndarray] = []
        self.registered = 0  # sweeps the odometry registered
        self.map_compactions = 0  # times the LiDAR map was thinned (``map_points`` then starts anew)
        self._map_count = 0
        self._map_limit = MAP_POINT_LIMIT
        self._finished = False

    @property
    def map_points(self) -> list[np.ndarray]:
        """The LiDAR map so far (odometry poses), in ``map``: one (N, 3) array per kept sweep; once it
        holds more than :data:`MAP_POINT_LIMIT` points, the first array is the map before that, thinned
        to one point per :data:`MAP_VOXEL_M` voxel (``map_compactions`` counts the times)."""
        return self._map_points

    def _add_map_points(self, points_map: np.ndarray) -> None:
        self._map_points.append(points_map)
        self._map_count += len(points_map)
        if self._map_count <= self._map_limit:
            return
        thinned = voxel_thin(np.concatenate(self._map_points), MAP_VOXEL_M)
        self._map_points = [thinned]
        self._map_count = len(thinned)
        self._map_limit = max(MAP_POINT_LIMIT, 2 * self._map_count)  # a large place: thin less often
        self.map_compactions += 1

    # ------------------------------------------------------------------ messages

    def on_scan(self, scan: LidarScan) -> np.ndarray | None:
        """A LiDAR sweep: registered by the odometry; images now behind its pose are fused.
        Returns the sweep's ``T_map_base`` (None when the odometry skipped it)."""
        t0 = time.perf_counter()
        pose = self.odometry.process(scan)
        t1 = time.perf_counter()
        self.timing["odometry"] += t1 - t0
        if pose is not None:
            self.registered += 1
            points = getattr(self.odometry, "last_points_base", None)
            if self.registered % MAP_EVERY == 1 and points is not None:
                self._add_map_points(transform_points(pose, points[::MAP_POINT_STRIDE]))
        if self.loop_closer is not None:
            self.loop_closer.on_scan(self.odometry, pose)
        if self._pending:
            last = self._last_pose_stamp()
            if last is not None:
                self._fuse_pending(upto=last)
        self.timing["fusion"] += time.perf_counter() - t1
        return pose

    def _last_pose_stamp(self) -> float | None:
        """The odometry's newest pose stamp (its optional ``last_stamp()``: no copy of the trajectory)."""
        last = getattr(self.odometry, "last_stamp", None)
        if callable(last):
            return last()
        stamps = check_trajectory(self.odometry, self.odometry.trajectory())[0]
        return float(stamps[-1]) if len(stamps) else None

    def on_image(self, frame: CameraFrame, detections: Sequence[Detection] | None = None) -> list[Detection] | None:
        """A camera image: detected (every ``detect_every``-th one), its detections wait for a pose.
        Returns the detections, or None when the detector did not run on this image.

        ``detections``: the image's detections when they were found elsewhere (another thread, a
        cache); the detector is not run and ``detect_every`` does not apply."""
        if self.loop_closer is not None:
            self.loop_closer.on_image(frame)
        if detections is None:
            run = self.detector is not None and self.images % self.detect_every == 0 \
                and (self.keyframes is None or self.keyframes.passes(frame))
            self.images += 1
            if not run:
                return None
            t0 = time.perf_counter()
            detections = detect(self.detector, frame)
            self.timing["detection"] += time.perf_counter() - t0
        else:
            self.images += 1
            detections = list(detections)
            if self.keyframes is not None:
                self.keyframes.mark(frame)
        keep_frame = self.map_objects and (self.retirement is not None or self.count_views)
        self._pending.append(_Waiting(self.detected_images, float(frame.stamp), detections,
                                      frame if keep_frame else None))
        self.detected_images += 1
        return detections

    def on_wheel_odometry(self, msg: WheelOdometry) -> None:
        self.wheel.add(msg)
        if self.keyframes is not None:
            self.keyframes.on_wheel_odometry(msg)
        if self._odometry_wheel is not None:
            self._odometry_wheel(msg)

    def on_message(self, msg) -> np.ndarray | list[Detection] | None:
        """Any of the three messages, dispatched by type (what ``on_scan`` / ``on_image`` return)."""
        if isinstance(msg, LidarScan):
            return self.on_scan(msg)
        if isinstance(msg, CameraFrame):
            return self.on_image(msg)
        if isinstance(msg, WheelOdometry):
            return self.on_wheel_odometry(msg)
        raise TypeError(f"expected a LidarScan, CameraFrame or WheelOdometry, got {type(msg).__name__}")

    # ------------------------------------------------------------------ the end

    def finish(self) -> PipelineResult:
        """Fuse the images still waiting (where a pose is known), let the loop closer correct the
        trajectory and place the map again, set the store's floor from the odometry and publish."""
        if self._finished:
            raise RuntimeError("DopeSlam.finish() was already called")
        self._finished = True
        t0 = time.perf_counter()
        self._fuse_pending(upto=None)
        stamps, poses_odom = check_trajectory(self.odometry, self.odometry.trajectory())
        poses, store, map_points = poses_odom, self.store, self._map_points
        if self.loop_closer is not None and len(stamps):
            poses = self.loop_closer.finish(stamps, poses_odom)
            if self.map_objects:
                store = self.loop_closer.refuse(ObjectStore(dims=self.dims, policy=self.policy),
                                                self.odometry.pose_at, self.T_base_cam)
                if self.retirement is not None:  # what was seen empty stays retired on the new trajectory
                    carry_over(self.store, store, self.retirement.config.revive_sightings)
                carry_views(self.store, store)
            map_points = self.loop_closer.map_points()
        floor = getattr(self.odometry, "floor_plane_map", None)
        store.floor = floor() if callable(floor) else None
        store.publish()
        self.store = store
        self.timing["fusion"] += time.perf_counter() - t0
        ws, wp = self.wheel.trajectory()
        return PipelineResult(store, stamps, poses, poses_odom, ws, wp, map_points, self._observations, self.unposed)

    # ------------------------------------------------------------------ fusion

    def _fuse_pending(self, upto: float | None) -> None:
        """Fuse the waiting images with stamps up to ``upto`` (all when None); keep the later ones."""
        keep = []
        for img in self._pending:
            if upto is not None and img.stamp > upto:
                keep.append(img)
                continue
            self._fuse_image(img)
        self._pending = keep

    def _fuse_image(self, img: _Waiting) -> None:
        poses: dict[float, np.ndarray | None] = {}  # an image's detections share its stamp: one lookup

        def pose_at(t: float):
            if t not in poses:
                poses[t] = check_pose(self.odometry, t, self.odometry.pose_at(t))
            return poses[t]

        fused, seen = [], set()
        for det in img.detections:
            if pose_at(det.stamp) is None:
                self.unposed += 1
                fused.append(None)
                continue
            obs = fuse(det, pose_at, self.T_base_cam)
            fused.append(obs)
            if self.map_objects:
                obj = self.store.add(obs)
                if obj is not None and obs.fpr_pass:  # a detection FPR rejected is no sighting (retirement)
                    seen.add(obj.id)
            if self.loop_closer is not None:
                self.loop_closer.on_fused(det)
            if self.keep_observations:
                self._observations.append(obs)
        if img.frame is not None and self.map_objects:
            T_map_base = pose_at(img.stamp)
            if T_map_base is not None:
                T_map_cam = T_map_base @ self.T_base_cam
                if self.count_views:
                    count_views(self.store, T_map_cam, img.frame.info, img.frame.depth_m, seen)
                if self.retirement is not None:
                    self.retirement.view(self.store, T_map_cam, img.frame.info, img.frame.depth_m, seen, img.stamp)
        if self.on_fused_image is not None:
            self.on_fused_image(FusedImage(img.index, img.stamp, pose_at(img.stamp), img.detections, fused))
