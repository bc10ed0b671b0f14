"""The DOPESLAM pipeline: sensor messages in time order in, an object map and a trajectory out.

    LidarScan        -> odometry (T_map_base per sweep)
    CameraFrame      -> detector (DOPE + FPR) -> waits for a pose -> fusion -> object store
    WheelOdometry    -> kept as a second trajectory (for comparison; the map does not use it)
    finish()         -> the last images fused, the store's floor set from the odometry, labels published

One rule for the images: an image's detections are fused once the odometry has a pose *after* the
image's stamp (the next registered sweep), so the robot pose at the image is interpolated between
two sweeps, never extrapolated from a stale one. At ``finish`` the images still waiting are fused if
the odometry gives a pose at their stamp (its bounded extrapolation past the last sweep), else
dropped and counted in ``unposed``.

Where the messages come from (a simulator, a rosbag, a robot) is not this module's business, nor is
scoring: ``on_image`` returns the image's detections so a harness can score them against its truth.
The components are the :mod:`stack.interfaces` protocols, so other people's odometry, detector,
labelling policy or loop closer plug in without changes here.
"""
from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from stack.fusion import fuse
from stack.interfaces import Detector, LoopCloser, Odometry
from stack.lidar_slam import WheelOdometryTrack
from stack.messages import CameraFrame, Detection, LidarScan, WheelOdometry
from stack.object_store import ObjectStore, Observation
from stack.retire import RetireConfig, Retirement
from stack.transforms import transform_points

MAP_EVERY = 5  # every 5th registered sweep goes into the LiDAR map (a picture, not used for labels) ...
MAP_POINT_STRIDE = 4  # ... with every 4th of its points


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


class DopeSlam:
    """Odometry + detector + fusion + object store, fed one message at a time.

    ``odometry``, ``detector``: see :mod:`stack.interfaces`. ``T_base_cam``: the camera's mounting
    (``camera_color_optical_frame`` in ``base_link``). ``dims``: cuboid size per class, for the store
    (every class the detector reports must be there). ``policy``: a labelling policy's registered
    name (:data:`stack.object_store.POLICIES`). ``loop_closer``: optional, see
    :class:`stack.interfaces.LoopCloser`. ``detect_every``: run the detector on every n-th image
    only. ``keep_observations``: keep every fused observation in the result. ``retire``: retire map
    objects whose place the depth images show empty (:mod:`stack.retire`); None: never.
    """

    def __init__(self, odometry: Odometry, detector: Detector, T_base_cam: np.ndarray,
                 dims: Mapping[str, Sequence[float]], policy: str = "robust-mean",
                 loop_closer: LoopCloser | None = None, detect_every: int = 1, keep_observations: bool = False,
                 retire: RetireConfig | None = None):
        if not isinstance(detector, Detector):
            raise TypeError(f"detector {type(detector).__name__} has no detect(frame) method")
        if detect_every < 1:
            raise ValueError(f"detect_every must be >= 1, got {detect_every}")
        self.odometry = odometry
        self.detector = detector
        self.T_base_cam = np.asarray(T_base_cam, dtype=float)
        self.dims = dict(dims)
        self.policy = policy
        self.loop_closer = loop_closer
        self.detect_every = int(detect_every)
        self.keep_observations = keep_observations
        self.retirement = Retirement(retire) if retire is not None else None
        self._views: list[CameraFrame] = []  # detected images waiting for a pose (retirement check)
        self.store = ObjectStore(dims=self.dims, policy=policy)
        self.wheel = WheelOdometryTrack()
        self.timing = {"odometry": 0.0, "detection": 0.0, "fusion": 0.0}  # seconds spent in each
        self.images = 0  # images received
        self.detected_images = 0  # images the detector ran on
        self.unposed = 0
        self._pending: list[Detection] = []  # detections waiting for a pose after their stamp
        self._observations: list[Observation] = []
        self._map_points: list[np.ndarray] = []
        self._registered = 0
        self._finished = False

    # ------------------------------------------------------------------ messages

    def on_scan(self, scan: LidarScan) -> np.ndarray | None:
        """A LiDAR sweep: registered by the odometry; images now behind its pose are fused.
        Returns the sweep's ``T_map_base`` (None when the odometry skipped it)."""
        t0 = time.perf_counter()
        pose = self.odometry.process(scan)
        t1 = time.perf_counter()
        self.timing["odometry"] += t1 - t0
        if pose is not None:
            self._registered += 1
            points = getattr(self.odometry, "last_points_base", None)
            if self._registered % MAP_EVERY == 1 and points is not None:
                self._map_points.append(transform_points(pose, points[::MAP_POINT_STRIDE]))
        if self.loop_closer is not None:
            self.loop_closer.on_scan(self.odometry, pose)
        if self._pending or self._views:
            stamps = self.odometry.trajectory()[0]
            if len(stamps):
                self._fuse_pending(upto=float(stamps[-1]))
        self.timing["fusion"] += time.perf_counter() - t1
        return pose

    def on_image(self, frame: CameraFrame) -> list[Detection] | None:
        """A camera image: detected (every ``detect_every``-th one), its detections wait for a pose.
        Returns the detections, or None when the detector did not run on this image."""
        if self.loop_closer is not None:
            self.loop_closer.on_image(frame)
        run = self.images % self.detect_every == 0
        self.images += 1
        if not run:
            return None
        t0 = time.perf_counter()
        detections = list(self.detector.detect(frame))
        self.timing["detection"] += time.perf_counter() - t0
        self.detected_images += 1
        self._pending.extend(detections)
        if self.retirement is not None:
            self._views.append(frame)
        return detections

    def on_wheel_odometry(self, msg: WheelOdometry) -> None:
        self.wheel.add(msg)

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
        stamps, poses_odom = self.odometry.trajectory()
        poses, store, map_points = poses_odom, self.store, self._map_points
        if self.loop_closer is not None and len(stamps):
            poses = self.loop_closer.finish(stamps, poses_odom)
            store = self.loop_closer.refuse(ObjectStore(dims=self.dims, policy=self.policy), self.odometry.pose_at,
                                            self.T_base_cam)
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
        """Fuse the waiting detections with stamps up to ``upto`` (all when None); keep the later ones."""
        keep, seen = [], {}
        for det in self._pending:
            if upto is not None and det.stamp > upto:
                keep.append(det)
                continue
            if self.odometry.pose_at(det.stamp) is None:
                self.unposed += 1
                continue
            obs = fuse(det, self.odometry.pose_at, self.T_base_cam)
            obj = self.store.add(obs)
            if obj is not None:
                seen.setdefault(det.stamp, set()).add(obj.id)
            if self.loop_closer is not None:
                self.loop_closer.on_fused(det)
            if self.keep_observations:
                self._observations.append(obs)
        self._pending = keep
        waiting = []
        for frame in self._views:
            if upto is not None and frame.stamp > upto:
                waiting.append(frame)
                continue
            T_map_base = self.odometry.pose_at(frame.stamp)
            if T_map_base is not None:
                self.retirement.view(self.store, T_map_base @ self.T_base_cam, frame.info, frame.depth_m,
                                     seen.get(frame.stamp, set()), frame.stamp)
        self._views = waiting
