"""``dopeslam replay``: the stack offline on a rosbag, in the paper's loose-coupled passes (section 3.3).

1. Odometry: KISS-ICP (``stack.lidar_slam.LidarOdometry``) over every scan of the bag.
2. Detection: DOPE (+ FPR) over every image; it needs no pose, so it runs at the same time as
   pass 1 (a second reader on the same bag, in a thread) when ``parallel``.
3. Fusion: each detection is carried into ``map`` with the robot pose interpolated from the
   finished trajectory at the image's stamp, then added to the object store in stamp order.

The outputs are those of ``dopeslam run`` (report.json, labels.xlsx/.json, TUM trajectories,
map.png, results bag). Scoring needs ground truth and appears only for what the bag carries:
trajectory scores with ``/ground_truth/base_pose``, label scores with ``/ground_truth/objects``,
detection precision and recall with ``/ground_truth/image_objects``. A real robot's bag gets the
map, the labels and the trajectory, and no scores.

Replaying the bag that ``run_episode(..., bag_writer=...)`` recorded gives that run's results:
the live run fuses each image with the pose interpolated between the scans around it as well
(images wait for the next scan), and before the first scan holds the first pose, as here.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np

from stack.errors import OutputError
from stack.fusion import fuse
from stack.lidar_slam import LidarOdometry, LidarOdometryConfig, WheelOdometryTrack
from stack.messages import CameraFrame, Detection
from stack.metrics import write_tum
from stack.object_store import ObjectStore, Observation
from stack.pipeline import MAP_EVERY, MAP_POINT_STRIDE  # as the live run: the same LiDAR map picture
from stack.transforms import transform_points
from testbed.bags import BagReader, MissingTopicError
from testbed.bags import topics as T
from testbed.record import RESULTS_BAG_NAME, image_truth_from_json, write_results_bag
from testbed.run import DetectionLog, _map_png, candidate_rows, score_detections, score_labels, score_trajectory
from testbed.scoring import summary_line
from testbed.io import check_new_output, edited_objects, output_dir, write_json

log = logging.getLogger(__name__)


@dataclass
class BagTopics:
    """Topic overrides (None: found by the drivers' usual names, see ``testbed/bags/topics.py``), and
    what the reader takes when ``/tf_static`` is missing or wrong: the base frame and the extrinsics
    (4x4 ``T_base_lidar`` / ``T_base_camera``); ``max_bad_messages``: how many messages per topic
    that cannot be converted are skipped (and reported) before the replay stops."""

    lidar: str | None = None
    rgb: str | None = None
    depth: str | None = None
    camera_info: str | None = None
    base_frame: str | None = None
    T_base_lidar: np.ndarray | None = None
    T_base_camera: np.ndarray | None = None
    max_bad_messages: int = 10


class BagImageTruth:
    """Per-image ground truth from ``/ground_truth/image_objects``: ``image_truth(frame)`` gives what
    ``Episode.image_truth`` gave for that frame when it was recorded."""

    def __init__(self, bag: BagReader):
        self.path = bag.path
        self._by_ns: dict[int, list[dict]] = {}
        for _, _, msg in bag.messages([T.GT_IMAGE_OBJECTS]):
            stamp, truths = image_truth_from_json(msg.data)
            self._by_ns[int(round(stamp * 1e9))] = truths

    def __len__(self) -> int:
        return len(self._by_ns)

    def image_truth(self, frame: CameraFrame) -> list[dict]:
        key = int(round(frame.stamp * 1e9))
        truths = self._by_ns.get(key)
        if truths is None:
            raise KeyError(f"{self.path}: {T.GT_IMAGE_OBJECTS} has no entry for the image at {frame.stamp:.9f} s")
        return truths


# --- pass 1: odometry ---------------------------------------------------------------------------

@dataclass
class OdometryPass:
    odom: LidarOdometry
    map_points: list[np.ndarray] = field(default_factory=list)  # map frame, as the live run collects them
    seconds: float = 0.0  # odometry only
    read_seconds: float = 0.0  # reading and decoding the scans
    scans: int = 0


def odometry_pass(bag: BagReader, config: LidarOdometryConfig | None = None, loop_closer=None) -> OdometryPass:
    """KISS-ICP over every scan of ``bag`` (an open reader). With ``loop_closer`` (a
    ``testbed.loop_closing.LoopClosingRun``) the colour images are read too, in stamp order with the
    scans, and both go to the loop closer as they do in a live run."""
    res = OdometryPass(LidarOdometry(bag.T_base_velodyne, config))
    odom = res.odom
    t_last = time.perf_counter()
    source = bag.scans() if loop_closer is None else bag.frames(lidar=True, camera=True, odometry=False)
    for scan in source:
        t0 = time.perf_counter()
        res.read_seconds += t0 - t_last
        if isinstance(scan, CameraFrame):
            loop_closer.on_image(scan)
            t_last = time.perf_counter()
            continue
        pose = odom.process(scan)
        if loop_closer is not None:
            loop_closer.on_scan(odom, pose)
        res.scans += 1
        if pose is not None and len(odom) % MAP_EVERY == 1 and odom.last_points_base is not None:
            res.map_points.append(transform_points(pose, odom.last_points_base[::MAP_POINT_STRIDE]))
        t_last = time.perf_counter()
        res.seconds += t_last - t0
        if res.scans % 100 == 0:
            log.info("odometry: %d scans (t = %.1f s)", res.scans, scan.stamp)
    if not len(odom):
        raise MissingTopicError(bag.path, "lidar", f"scans on {bag.lidar_topic} that odometry can register",
                                bag.topics, f"{res.scans} scan(s) read, none registered")
    return res


# --- pass 2: detection ----------------------------------------------------------------------------

@dataclass
class DetectionPass:
    detections: list[Detection] = field(default_factory=list)  # in image order
    flags: list[bool] = field(default_factory=list)  # per detection: correct (when scored)
    dlog: DetectionLog = field(default_factory=DetectionLog)
    images: int = 0
    read_seconds: float = 0.0


def detection_pass(bag: BagReader, detector, dope_every: int = 1,
                   truth: BagImageTruth | None = None) -> DetectionPass:
    """``detector.detect`` over every ``dope_every``-th image of ``bag``; scored when ``truth``."""
    res = DetectionPass()
    dlog = res.dlog
    t_last = time.perf_counter()
    for frame in bag.camera_frames():
        t0 = time.perf_counter()
        res.read_seconds += t0 - t_last
        if res.images % dope_every == 0:
            dets = detector.detect(frame)
            t1 = time.perf_counter()
            dlog.seconds += t1 - t0
            dlog.frames += 1
            if truth is not None:
                res.flags.extend(score_detections(dlog, dets, truth.image_truth(frame)))
            else:
                dlog.predictions += sum(d.fpr_pass for d in dets)
            res.detections.extend(dets)
        res.images += 1
        t_last = time.perf_counter()
        if res.images % 100 == 0:
            log.info("detection: %d images (t = %.1f s), %d detections", res.images, frame.stamp,
                     len(res.detections))
    return res


# --- pass 3: fusion ---------------------------------------------------------------------------------

def replay_pose_lookup(odom: LidarOdometry) -> Callable[[float], np.ndarray | None]:
    """``T_map_base`` at t from the finished trajectory, as the live run has it when it fuses.

    Between scans: interpolated; after the last: ``odom.pose_at`` (constant velocity, bounded);
    before the first scan: the first pose (the live run fuses those images right after the first
    scan, when no velocity is known yet), within ``max_extrapolation_s``; else None.
    """
    stamps, poses = odom.trajectory()
    t0, first = float(stamps[0]), poses[0]
    limit = odom.config.max_extrapolation_s

    def lookup(t: float) -> np.ndarray | None:
        if t < t0:
            return first.copy() if t >= t0 - limit else None
        return odom.pose_at(t)

    return lookup


def fuse_into_store(detections: list[Detection], lookup: Callable[[float], np.ndarray | None],
                    T_base_cam: np.ndarray, store: ObjectStore) -> tuple[list[Observation], int]:
    """Each detection into ``map`` at its image's pose and into ``store``, in stamp order.
    Returns (observations, detections without a pose)."""
    observations, unposed = [], 0
    for det in sorted(detections, key=lambda d: d.stamp):  # stable: images are in order already
        pose = lookup(det.stamp)
        if pose is None:
            unposed += 1
            continue
        obs = fuse(det, lambda _t, pose=pose: pose, T_base_cam)
        store.add(obs)
        observations.append(obs)
    return observations, unposed


# --- the whole replay ---------------------------------------------------------------------------------

def open_bag(path, topics: BagTopics, input_mode: str, need_camera: bool = True) -> BagReader:
    extra = {"base_frame": topics.base_frame} if topics.base_frame else {}
    bag = BagReader(path, lidar_topic=topics.lidar, rgb_topic=topics.rgb, depth_topic=topics.depth,
                    camera_info_topic=topics.camera_info, require_camera=need_camera,
                    T_base_lidar=topics.T_base_lidar, T_base_camera=topics.T_base_camera,
                    max_bad_messages=topics.max_bad_messages, **extra).open()
    if need_camera:
        have = bag.rgb_topic if input_mode == "rgb" else bag.depth_topic
        if have is None:
            bag.close()
            other = "--input depth" if input_mode == "rgb" else "--input rgb"
            raise MissingTopicError(bag.path, input_mode, f"a {input_mode} image topic (for --input {input_mode})",
                                    bag.topics, f"pass --{input_mode}-topic, or {other}")
    return bag


def _path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()) if len(poses) > 1 else 0.0


def replay_bag(bag_path, out_dir="out/replay", detector=None, input_mode: str = "rgb", stages: int = 6,
               fpr: bool = True, weights=None, policy: str = "robust-mean", topics: BagTopics | None = None,
               dope_every: int = 1, parallel: bool = True, write_outputs: bool = True,
               results_bag=None, keep_detections: bool = False, loop_closure: bool = False,
               vocabulary=None) -> dict:
    """Run the stack over a bag in passes; returns the report (written to OUT/report.json).

    ``loop_closure``: pass 1 also feeds the loop closer (key frames from the colour images, scans);
    the corrected trajectory then places the detections in pass 3, and replaces the odometry's in
    the outputs (the odometry-only ATE is reported beside it when the bag has ground truth)."""
    from sim.objects import load_catalog
    from testbed.run import make_detector

    topics = topics or BagTopics()
    out = Path(out_dir)
    if results_bag is not None:  # never over the input, whatever --force says
        check_new_output(results_bag, "--results-bag", force=True, inputs=[bag_path])
    if write_outputs and (out.resolve() == Path(bag_path).resolve() or Path(bag_path).resolve() in out.resolve().parents):
        raise OutputError(f"--out {out}: is, or lies inside, the input bag {bag_path}; choose another folder")
    kept = edited_objects(out) if write_outputs else []  # checked before any work starts
    wall0 = time.perf_counter()
    bag = open_bag(bag_path, topics, input_mode)
    try:
        log.info("%s", bag.describe())
        detector = detector or make_detector(input_mode, stages, fpr, weights)
        dims = {c: s.dims for c, s in load_catalog().items()}
        truth = BagImageTruth(bag) if bag.topics.get(T.GT_IMAGE_OBJECTS) == "std_msgs/msg/String" else None

        # passes 1 and 2: independent of each other
        odo_result: dict = {}

        lc = None
        if loop_closure:
            from testbed.loop_closing import LoopClosingRun

            lc = LoopClosingRun(vocabulary)
            if bag.rgb_topic is None:
                log.warning("%s: no colour images: the loop closer uses LiDAR key frames only", bag.path)

        def run_odometry() -> None:
            try:
                reader = open_bag(bag_path, topics, input_mode, need_camera=lc is not None) if parallel else bag
                try:
                    odo_result["pass"] = odometry_pass(reader, loop_closer=lc)
                finally:
                    if reader is not bag:
                        reader.close()
            except BaseException as exc:  # re-raised in the main thread
                odo_result["error"] = exc

        t_passes = time.perf_counter()
        if parallel:
            worker = threading.Thread(target=run_odometry, name="replay-odometry", daemon=True)
            worker.start()
            det = detection_pass(bag, detector, dope_every, truth)
            worker.join()
        else:
            run_odometry()
            if "error" not in odo_result:
                det = detection_pass(bag, detector, dope_every, truth)
        if "error" in odo_result:
            raise odo_result["error"]
        passes_wall = time.perf_counter() - t_passes
        odo: OdometryPass = odo_result["pass"]

        # loop closure: the corrected trajectory
        stamps, poses = odo.odom.trajectory()
        lookup = replay_pose_lookup(odo.odom)
        poses_odom = poses
        if lc is not None:
            poses = lc.finish(stamps, poses_odom)
            lookup = lc.pose_lookup(lookup)
            odo.map_points = lc.map_points()

        # pass 3: fusion
        t0 = time.perf_counter()
        store = ObjectStore(dims=dims, policy=policy)
        T_base_cam = bag.T_base_camera
        observations, unposed = fuse_into_store(det.detections, lookup, T_base_cam, store)
        store.floor = odo.odom.floor_plane_map()
        store.publish()
        fusion_s = time.perf_counter() - t0

        wheel = WheelOdometryTrack()
        if bag.odom_topic:
            for msg in bag.wheel_odometry():
                wheel.add(msg)
        wall = time.perf_counter() - wall0

        gt = bag.groundtruth
        span = _bag_span(bag, stamps)
        meta = bag.metadata
        report: dict = {
            "bag": str(bag.path), "source": meta.get("source", "rosbag"),
            "scenario": meta.get("scenario", bag.path.stem), "seed": meta.get("seed"), "light": meta.get("light"),
            "input": input_mode, "stages": stages, "fpr": fpr, "policy": policy,
            "topics": {"lidar": bag.lidar_topic, "rgb": bag.rgb_topic, "depth": bag.depth_topic,
                       "camera_info": bag.camera_info_topic, "odometry": bag.odom_topic},
            "ground_truth": {"trajectory": gt is not None, "objects": bool(gt is not None and gt.objects),
                             "images": truth is not None},
            "bag_seconds": span, "wall_seconds": wall, "real_time_factor": span / wall if wall > 0 else None,
            "parallel_passes": parallel,
            "time_split_s": {"odometry": odo.seconds, "odometry_reading": odo.read_seconds,
                             "dope": det.dlog.seconds, "image_reading": det.read_seconds,
                             "passes_wall": passes_wall, "fusion": fusion_s},
        }
        if bag.salvaged:
            report["salvaged"] = bag.salvaged
        if bag.bad_messages:  # skipped, counted and named (the detection reader's are in its log)
            report["bad_messages"] = bag.bad_message_summary()
        odometry = {"poses": int(len(stamps)), "scans": odo.scans, "path_length_m": _path_length(poses),
                    "odometry_hz": odo.odom.stats.hz}
        T_world_map = None
        if gt is not None:
            T_world_map = gt.T_world_base_at(stamps[0])
            odometry = {**score_trajectory(stamps, poses, gt, T_world_map), **odometry}
            if lc is not None:
                odometry.update(lc.summary(stamps, poses_odom, poses, T_world_map, gt.T_world_base_at))
        elif lc is not None:
            s = lc.closer.summary()
            odometry.update({"loop_closures": s["loop_closures"], "loop_candidates_rejected": s["loop_candidates_rejected"],
                             "loop_closure": {**s, "closures": [c.as_dict() for c in lc.closer.closures]}})
        if lc is not None:
            report["time_split_s"]["loop_closure"] = lc.seconds
        report["loop_closure"] = lc is not None
        report["odometry"] = odometry
        if gt is not None and len(wheel) > 1:
            ws, wp = wheel.trajectory()
            report["wheel_odometry"] = score_trajectory(ws, wp, gt, gt.T_world_base_at(ws[0]))
        dsum = det.dlog.summary()
        if truth is None:  # precision and recall need the truth per image: left out
            dsum = {k: dsum[k] for k in ("frames", "predictions", "fps")}
        dsum["detections_without_pose"] = unposed
        report["detection"] = dsum
        if gt is not None and gt.objects:
            labels, labels_summary = score_labels(store, gt.objects, T_world_map)
            report["labels"], report["labels_summary"] = labels, labels_summary
            report["candidates"] = candidate_rows(store, T_world_map)
        else:
            report["labels"] = [{"id": m.id, "class": m.cls, "label_xyz_map": [float(v) for v in m.xyz],
                                 "observations": m.observations, "status": m.status, "reason": m.reason}
                                for m in store]
            report["labels_summary"] = {"map_objects": len(store), "labels_in_map": len(store.labels()),
                                        "candidates": len(store.candidates())}

        if write_outputs:  # into a hidden sibling, renamed into place whole; report.json last
            with output_dir(out) as stage:
                store.keep_edited(kept)  # rows a person marked edited in the folder's store files
                store.save(stage / "labels.xlsx")
                store.save(stage / "labels.json")
                if gt is not None:
                    write_tum(stage / "estimate_tum.txt", stamps, T_world_map @ poses)
                    write_tum(stage / "groundtruth_tum.txt", stamps, gt.T_world_base_at(stamps))
                    if gt.objects:
                        shim = SimpleNamespace(groundtruth=SimpleNamespace(T_world_base=gt.T_world_base))
                        _map_png(stage / "map.png", shim, T_world_map, poses, odo.map_points, report["labels"], report)
                    else:
                        _map_png_untruthed(stage / "map.png", poses, odo.map_points, store, report, T_world_map)
                else:
                    write_tum(stage / "estimate_tum.txt", stamps, poses)
                    _map_png_untruthed(stage / "map.png", poses, odo.map_points, store, report)
                write_results_bag(results_bag or stage / RESULTS_BAG_NAME, store, odo.map_points, stamps, poses,
                                  T_world_map=T_world_map, objects=gt.objects if gt is not None and gt.objects else None)
                write_json(stage / "report.json", report)
        if keep_detections:
            report["_detections"] = list(zip(det.detections, det.flags)) if truth is not None else det.detections
            report["_store"] = store
            report["_observations"] = observations
            report["_trajectory"] = (stamps, poses)
            report["_T_world_map"] = T_world_map
        return report
    finally:
        bag.close()


def _bag_span(bag: BagReader, stamps: np.ndarray) -> float:
    """Seconds of sensor data: from the first to the last registered scan (+ one sweep)."""
    if len(stamps) < 2:
        return 0.0
    return float(stamps[-1] - stamps[0] + np.median(np.diff(stamps)))


def _map_png_untruthed(path, poses, map_points, store, report, T_world_map=None) -> None:
    """The map without ground truth: LiDAR map, trajectory and labels in ``map`` (or ``world``)."""
    from testbed.plots import plt, save

    T = np.eye(4) if T_world_map is None else T_world_map
    frame = "map" if T_world_map is None else "world"
    fig, ax = plt.subplots(figsize=(9, 6.5))
    if map_points:
        pts = transform_points(T, np.vstack(map_points))
        pts = pts[(pts[:, 2] > 0.05) & (pts[:, 2] < 2.0)] if T_world_map is not None else pts
        ax.scatter(pts[:, 0], pts[:, 1], s=0.2, c="0.55", label="LiDAR map")
    est = (T @ poses)[:, :2, 3]
    ax.plot(est[:, 0], est[:, 1], "b--", lw=1, label="LiDAR odometry")
    for m in store.labels():
        x, y = transform_points(T, m.xyz[None])[0, :2]
        ax.plot(x, y, "x", color="tab:blue", ms=7, mew=2)
        ax.annotate(f"{m.cls} {m.id}", (x, y), xytext=(5, 5), textcoords="offset points", fontsize=7)
    for m in store.candidates():
        x, y = transform_points(T, m.xyz[None])[0, :2]
        ax.plot(x, y, ".", color="0.6", ms=4)
    ax.plot([], [], "x", color="tab:blue", label="label")
    ax.plot([], [], ".", color="0.6", label="candidate (not published)")
    ax.set_title(f"{report['scenario']}: {len(store.labels())} labels, {len(store.candidates())} candidates "
                 "(no ground truth in the bag)")
    ax.set_aspect("equal")
    ax.legend(loc="lower left", fontsize=7)
    ax.set_xlabel(f"x (m, {frame})")
    ax.set_ylabel(f"y (m, {frame})")
    save(fig, path)


def print_replay_summary(report: dict) -> None:
    """``print_summary`` when the bag had ground truth; the unscored facts otherwise."""
    from testbed.run import print_summary

    rtf = report["real_time_factor"]
    print(f"{report['bag']}: {report['bag_seconds']:.1f} s of data replayed in {report['wall_seconds']:.1f} s "
          f"({'-' if rtf is None else f'{rtf:.2f}'}x real time)")
    if report["ground_truth"]["trajectory"] and report["ground_truth"]["objects"] and \
            report["ground_truth"]["images"]:
        print_summary({**report, "sim_seconds": report["bag_seconds"]})
        return
    o, d = report["odometry"], report["detection"]
    print(f"odometry: {o['poses']} poses over {o['path_length_m']:.1f} m"
          + (f", ATE {100 * o['ate_rmse_m']:.1f} cm" if "ate_rmse_m" in o else " (no ground truth: not scored)"))
    print(f"detection: {d['predictions']} predictions in {d['frames']} frames"
          + ("" if "precision" in d else " (no per-image ground truth: not scored)"))
    if "mean_error_m" in report["labels_summary"]:
        print(summary_line(report["labels_summary"]))
    else:
        print(f"{'id':>3} {'class':<12} {'x':>7} {'y':>7} {'z':>7}  status (map frame, not scored)")
        for r in report["labels"]:
            x, y, z = r["label_xyz_map"]
            print(f"{r['id']:>3} {r['class']:<12} {x:7.2f} {y:7.2f} {z:7.2f}  {r['status']}"
                  + (f" ({r['reason']})" if r["reason"] else ""))
