"""``dopeslam record``: an episode into a rosbag, with the topics the real drivers publish and the
simulator's ground truth on topics of its own; and the stack's results into a bag after a run.

What a recorded bag holds (topic names in ``testbed/bags/topics.py``):

* the robot: ``/velodyne_points``, the colour and aligned-depth images with their camera_info,
  ``/tf_static`` (base_link -> velodyne, base_link -> camera_color_optical_frame), wheel odometry
  and its ``/tf``;
* ground truth: base_link in ``world`` at every physics step (``/ground_truth/base_pose``), the
  objects' cuboids (``/ground_truth/objects``), and per camera frame the objects as the camera sees
  them (``/ground_truth/image_objects``: pose in the camera, visible fraction; what detection
  scoring needs, since a bag has no segmentation image);
* ``/dopeslam/metadata``: scenario, seed, light, the scenario itself.

:class:`EpisodeRecorder` streams an episode while it runs, so ``run_episode`` records the episode
it is scoring (``bag_writer=``) and ``record_episode`` records one without running the stack.
"""
from __future__ import annotations

import json
import logging
import math
import platform
import queue
import threading
import time
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from stack.messages import CameraFrame, LidarScan, WheelOdometry
from stack.transforms import voxel_thin
from testbed.bags import BagWriteError, BagWriter, Cuboid, bag_size
from testbed.bags import topics as T

log = logging.getLogger(__name__)

RESULTS_BAG_NAME = "results_bag"  # under a run's output folder: a ROS 2 bag (MCAP) of the stack's results
MAP_VOXEL_M = 0.05  # the results bag's LiDAR map is thinned to one point per voxel of this size


# --- per-image ground truth ------------------------------------------------------------------

def _floats(a: Any) -> list:
    """A flat list of floats for JSON, NaN as null (JSON has no NaN)."""
    return [None if not math.isfinite(v) else float(v) for v in np.asarray(a, dtype=float).ravel()]


def image_truth_json(stamp: float, truths: Sequence[dict]) -> str:
    """``Episode.image_truth`` of one frame as the JSON carried by ``/ground_truth/image_objects``."""
    objects = [{"name": t["name"], "cls": t["cls"], "T_cam_obj": _floats(t["T_cam_obj"]),
                "keypoints_px": _floats(t["keypoints_px"]), "in_front": bool(t["in_front"]),
                "visible_fraction": float(t["visible_fraction"]), "distance_m": float(t["distance_m"])}
               for t in truths]
    return json.dumps({"stamp": float(stamp), "frame_id": T.CAMERA, "objects": objects}, separators=(",", ":"))


def image_truth_from_json(text: str) -> tuple[float, list[dict]]:
    """(stamp, truths) with the fields and types ``Episode.image_truth`` gives."""
    data = json.loads(text)
    out = []
    for o in data["objects"]:
        out.append({"name": o["name"], "cls": o["cls"],
                    "T_cam_obj": np.array(o["T_cam_obj"], dtype=float).reshape(4, 4),
                    "keypoints_px": np.array([np.nan if v is None else v for v in o["keypoints_px"]],
                                             dtype=float).reshape(-1, 2),
                    "in_front": bool(o["in_front"]), "visible_fraction": float(o["visible_fraction"]),
                    "distance_m": float(o["distance_m"])})
    return float(data["stamp"]), out


def write_image_truth(writer: BagWriter, stamp: float, truths: Sequence[dict]) -> None:
    msg = writer.dialect.make("std_msgs/msg/String", data=image_truth_json(stamp, truths))
    writer.write_message(T.GT_IMAGE_OBJECTS, "std_msgs/msg/String", stamp, msg)


# --- the episode -------------------------------------------------------------------------------

def episode_metadata(ep) -> dict:
    """Facts of a recorded episode for ``/dopeslam/metadata``."""
    from importlib.metadata import PackageNotFoundError, version

    def ver(pkg: str) -> str | None:
        try:
            return version(pkg)
        except PackageNotFoundError:
            return None

    sc = ep.sc
    return {"source": "dopeslam record (simulation)", "scenario": sc.name, "scenario_file": sc.source,
            "seed": ep.seed, "duration_s": ep.duration, "light": ep.light, "renderer": ep.renderer,
            "scenario_config": sc.model_dump(mode="json"),
            "versions": {"dopeslam-testbed": ver("dopeslam-testbed"), "rosbags": ver("rosbags"),
                         "pybullet": ver("pybullet"), "python": platform.python_version()}}


class EpisodeRecorder:
    """Streams an :class:`~sim.episode.Episode` into an open :class:`BagWriter`.

    Call ``write(msg)`` for every message of ``ep.frames()`` as it comes, then ``finish()``.
    The first ``write`` puts the latched topics first (metadata, ``/tf_static``, the objects'
    ground truth); each ``write`` adds the base poses the episode has produced since the last one,
    and for a camera frame the per-image ground truth (``truths``: ``ep.image_truth(frame)`` when
    the caller has it already, else it is computed).

    ``background``: conversion, serialisation, compression and disk writes run in a thread of
    their own (compression and I/O release the GIL, so on two cores they overlap the simulation);
    at most ``queue_size`` messages wait, and an error there is raised by the next ``write`` or by
    ``finish``, which waits for everything to be written. ``seconds`` is the wall time the caller
    spent in ``write``/``finish`` (what recording adds to its loop), ``cpu_seconds`` the CPU time
    of the recording in either thread.
    """

    def __init__(self, writer: BagWriter, ep, image_truth: bool = True, background: bool = True,
                 queue_size: int = 32):
        self.writer = writer
        self.ep = ep
        self.image_truth = image_truth
        if writer.format == "ros2" and writer.storage == "sqlite3":
            background = False  # an SQLite connection may be used only by the thread that opened it
        self.seconds = 0.0
        self.cpu_seconds = 0.0
        self._gt_written = 0
        self._started = False
        self._finished = False
        self._queue: queue.Queue | None = queue.Queue(maxsize=queue_size) if background else None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._worker_cpu = 0.0

    def write(self, msg: LidarScan | CameraFrame | WheelOdometry, truths: Sequence[dict] | None = None) -> None:
        t0, c0 = time.perf_counter(), time.thread_time()
        if self._finished:
            raise RuntimeError("EpisodeRecorder.write after finish()")
        self._start()
        self._submit_ground_truth_poses()
        self._submit(self.writer.write, msg)
        if self.image_truth and isinstance(msg, CameraFrame):
            self._submit(write_image_truth, self.writer, msg.stamp,
                         self.ep.image_truth(msg) if truths is None else truths)
        self.seconds += time.perf_counter() - t0
        self.cpu_seconds += time.thread_time() - c0

    def finish(self) -> None:
        """Write the remaining ground truth and wait until everything is in the writer."""
        t0, c0 = time.perf_counter(), time.thread_time()
        if not self._finished:
            self._start()
            self._submit_ground_truth_poses(upto_message=False)
            self._finished = True
            if self._thread is not None:
                self._queue.put(None)
                self._thread.join()
                self.cpu_seconds += self._worker_cpu
            self._raise_pending()
        self.seconds += time.perf_counter() - t0
        self.cpu_seconds += time.thread_time() - c0

    # --- internals ---
    def _start(self) -> None:
        if self._started:
            return
        self._started = True
        if self._queue is not None:
            self._thread = threading.Thread(target=self._work, name="bag-recorder", daemon=True)
            self._thread.start()
        ep = self.ep
        self._submit(self.writer.write_metadata, 0.0, episode_metadata(ep))
        self._submit(self.writer.write_extrinsics, ep.T_base_velodyne, ep.T_base_camera, 0.0,
                     T.VELODYNE, ep.camera_info.frame_id)
        self._submit(self.writer.write_ground_truth_objects, 0.0, list(ep.objects))

    def _submit_ground_truth_poses(self, upto_message: bool = True) -> None:
        gt = self.ep.groundtruth
        n = len(gt)
        if upto_message:  # up to the message being written (``Episode.frames``), not beyond
            n = min(n, getattr(self.ep, "groundtruth_rows", n))
        if n > self._gt_written:
            stamps, poses = gt.window(self._gt_written, n)
            self._gt_written = n
            self._submit(self._write_poses, stamps, poses)

    def _write_poses(self, stamps: list, poses: list) -> None:
        for t, T_world_base in zip(stamps, poses):
            self.writer.write_ground_truth_pose(t, T_world_base)

    def _submit(self, fn, *args) -> None:
        self._raise_pending()
        if self._queue is None:
            fn(*args)
        else:
            self._queue.put((fn, args))

    def _raise_pending(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def _work(self) -> None:
        c0 = time.thread_time()
        assert self._queue is not None
        while True:
            item = self._queue.get()
            if item is None:
                break
            if self._error is not None:
                continue  # after an error: drain, so the episode never blocks on a full queue
            fn, args = item
            try:
                fn(*args)
            except BaseException as exc:  # handed to the episode's thread by the next write/finish
                self._error = exc
        self._worker_cpu = time.thread_time() - c0


def record_episode(scenario=None, bag: Path | str = "out/episode", format: str | None = None,
                   storage: str = "mcap", seed: int | None = None, duration: float | None = None,
                   light: float | None = None, overwrite: bool = False, compress: bool = True,
                   faults=(), images: str = "compressed", lidar: str | None = None) -> dict:
    """Run an episode (no stack) and write it to ``bag``; returns a summary with the timing.
    ``faults``: ``NAME=VALUE`` sensor faults over the scenario's ``[faults]`` (``sim.faults``): the
    bag holds the messages as the faulty drivers publish them. ``images``: ``compressed`` (lossless PNG
    CompressedImage topics, ``testbed.bags.images``) or ``raw`` (sensor_msgs/Image). ``lidar``: ``points``
    (PointCloud2), ``packets`` (the VLP-32C's packets, ``stack.velodyne``: the simulated Velodyne then
    publishes packets) or None (packets where the scenario's ``[sensors] lidar_packets`` is on)."""
    from sim.faults import FaultInjector, parse_overrides

    from sim.episode import Episode
    from sim.render import render_worker_wanted

    bag = Path(bag)
    wall0 = time.perf_counter()
    # rendered in this process unless DOPESLAM_RENDER_WORKER=1 (the same bag either way; the writer's
    # thread, which encodes the images, is what a recording waits for: no faster with the worker)
    if lidar not in (None, "points", "packets"):
        raise BagWriteError(bag, f"lidar {lidar!r}: expected 'points' or 'packets'")
    with Episode(scenario, seed=seed, duration=duration, light=light, render_worker=render_worker_wanted(False),
                 lidar_packets=True if lidar == "packets" else None) as ep:
        lidar = lidar or ("packets" if ep.lidar_packets else "points")
        writer = BagWriter(bag, format, storage, compress=compress, overwrite=overwrite, images=images, lidar=lidar)
        with writer:
            rec = EpisodeRecorder(writer, ep)
            last_log = time.perf_counter()
            fault_set = parse_overrides(faults or (), ep.sc.faults)
            injector = FaultInjector(fault_set, ep.seed) if fault_set.active else None
            for msg in (ep.frames() if injector is None else injector.apply(ep.frames())):
                rec.write(msg)
                if time.perf_counter() - last_log > 15:
                    last_log = time.perf_counter()
                    log.info("recording t = %5.1f s of %.0f s (%d messages)", msg.stamp, ep.duration,
                             sum(writer.counts.values()))
            rec.finish()
        wall = time.perf_counter() - wall0
        return {"bag": str(bag), "format": writer.describe(), "scenario": ep.sc.name, "seed": ep.seed,
                "sim_seconds": ep.sim_seconds, "wall_seconds": wall, "recording_seconds": rec.seconds,
                "recording_cpu_seconds": rec.cpu_seconds,
                "recording_share": rec.seconds / wall if wall > 0 else None,
                "bytes": bag_size(bag), "messages": dict(sorted(writer.counts.items())),
                "faults": None if injector is None else {"settings": fault_set.active, "counts": injector.counts}}


# --- the stack's results -------------------------------------------------------------------------

def store_cuboids(store) -> list[Cuboid]:
    """The object store's published labels as cuboids in ``map`` (name ``<class>_<id>``); candidates
    are not labels and are left out."""
    return [Cuboid(f"{m.cls}_{m.id}", m.cls, m.T_map_obj, np.asarray(m.size, dtype=float)) for m in store.labels()]


def write_results_bag(path: Path | str, store, map_points: Iterable[np.ndarray] | np.ndarray | None,
                      stamps: np.ndarray, T_map_base: np.ndarray, *, T_world_map: np.ndarray | None = None,
                      objects=None, format: str | None = None, storage: str = "mcap",
                      overwrite: bool = True) -> Path:
    """The stack's results as a bag RViz or Foxglove shows as an annotated map (fixed frame ``map``).

    ``/dopeslam/labels`` (MarkerArray: one cuboid per stored object), ``/dopeslam/map`` (the LiDAR
    map, PointCloud2, thinned to ``MAP_VOXEL_M`` voxels), ``/dopeslam/trajectory`` (nav_msgs/Path of
    base_link). With ``T_world_map`` also ``/tf_static`` world -> map, and with ``objects`` the true
    cuboids on ``/ground_truth/objects``, so labels and truth can be seen side by side.
    """
    path = Path(path)
    stamps = np.asarray(stamps, dtype=float)
    end = float(stamps[-1]) if len(stamps) else 0.0
    if map_points is None:
        pts = np.zeros((0, 3))
    elif isinstance(map_points, np.ndarray):
        pts = map_points.reshape(-1, 3)
    else:
        chunks = [np.asarray(p).reshape(-1, 3) for p in map_points]
        pts = np.vstack(chunks) if chunks else np.zeros((0, 3))
    with BagWriter(path, format, storage, overwrite=overwrite) as w:
        if T_world_map is not None:
            w.write_tf_static(end, [(T.WORLD, T.MAP_FRAME, np.asarray(T_world_map, dtype=float))])
        w.write_labels(end, store_cuboids(store))
        w.write_map(end, voxel_thin(pts, MAP_VOXEL_M))
        d = w.dialect
        poses = [d.make("geometry_msgs/msg/PoseStamped", header=d.header(int(round(t * 1e9)), T.MAP_FRAME),
                        pose=d.pose(P)) for t, P in zip(stamps, np.asarray(T_map_base).reshape(-1, 4, 4))]
        path_msg = d.make("nav_msgs/msg/Path", header=d.header(int(round(end * 1e9)), T.MAP_FRAME), poses=poses)
        w.write_message(T.TRAJECTORY, "nav_msgs/msg/Path", end, path_msg, latched=True)
        if objects is not None:
            w.write_ground_truth_objects(end, objects)
    return path
