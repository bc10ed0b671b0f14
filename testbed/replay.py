"""``dopeslam replay``: the stack offline on a rosbag. The bag is the message source; the stack's
pipeline (:class:`stack.pipeline.DopeSlam`) gets its scans, images and wheel odometry in stamp order,
as ``dopeslam run`` gives it the simulator's, with the same rule for images that wait for a pose.

The detector needs no pose, so by default it runs ahead of the pipeline on a second reader of the
same bag (the paper's loose coupling, section 3.3): the bundled DOPE detector in a child process
(:mod:`testbed.replay_detection`), any other in a thread (:class:`DetectionAhead`); the pipeline
then fuses each image's detections when its turn in the stream comes. ``parallel=False``
(``--sequential``) runs the detector in the message loop instead.

The outputs are those of ``dopeslam run`` (report.json, labels.xlsx/.json, TUM trajectories,
map.png, results bag). Scoring needs ground truth and appears only for what the bag carries:
trajectory scores with ``/ground_truth/base_pose``, label scores with ``/ground_truth/objects``,
detection precision and recall with ``/ground_truth/image_objects``. A real robot's bag gets the
map, the labels and the trajectory, and no scores.

Replaying the bag that ``run_episode(..., bag_writer=...)`` recorded gives that run's results: the
same pipeline gets the same messages.
"""
from __future__ import annotations

import heapq
import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np

from stack.errors import OutputError
from stack.interfaces import Detector, check_trajectory, detect
from stack.keyframes import keyframe_gate
from stack.messages import CameraFrame, LidarScan
from stack.metrics import write_tum
from stack.pipeline import DopeSlam
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

    def get(self, frame: CameraFrame) -> list[dict] | None:
        """The frame's truth, or None when the bag has none for it (its entry was in a damaged chunk)."""
        return self._by_ns.get(int(round(frame.stamp * 1e9)))

    def image_truth(self, frame: CameraFrame) -> list[dict]:
        truths = self.get(frame)
        if truths is None:
            raise KeyError(f"{self.path}: {T.GT_IMAGE_OBJECTS} has no entry for the image at {frame.stamp:.9f} s")
        return truths


# --- the message stream ---------------------------------------------------------------------------

HELPER_DEPTH = 2  # images the helper detection process may hold at once


def detected_images(reader: BagReader, detector, every: int, gate, helper=None):
    """Per image of ``reader``: ``(frame, detections or None when not detected, seconds reading it,
    seconds detecting)``. The detector runs on every ``every``-th image that ``gate`` (a
    :class:`stack.keyframes.KeyframeGate`, fed the bag's wheel odometry; None: every image) passes.

    ``helper``: a :class:`testbed.detection_process.DetectionProcess` with the same detector. An image
    goes to it while it holds fewer than :data:`HELPER_DEPTH`, else ``detector`` detects it here; so
    the helper, which only detects, takes more of the images than this process, which also reads and
    decodes them all. The images, their order and their detections are those without it; an image in
    the helper holds back at most four later ones."""
    frames = reader.camera_frames() if gate is None else reader.frames(lidar=False, camera=True, odometry=True)
    t_last, i = time.perf_counter(), -1
    held: deque = deque()  # [frame, detections or the helper's job, reading s, detecting s], in image order
    in_helper: deque = deque()  # (entry, its image index) of the images in the helper, oldest first

    def collect():
        entry, _ = in_helper.popleft()
        entry[1], entry[3] = entry[1].result()

    for frame in frames:
        if not isinstance(frame, CameraFrame):
            gate.on_wheel_odometry(frame)
            continue
        i += 1
        t0 = time.perf_counter()
        entry = [frame, None, t0 - t_last, 0.0]
        if i % every == 0 and (gate is None or gate.passes(frame)):
            if helper is not None and helper.fits(frame) and helper.unfinished() < HELPER_DEPTH:
                entry[1] = helper.submit(frame)
                in_helper.append((entry, i))
            else:
                entry[1] = detect(detector, frame)
                entry[3] = time.perf_counter() - t0
        held.append(entry)
        # the helper's images back: those it has done, and one that four later images have waited behind
        while in_helper and (in_helper[0][0][1].done() or i - in_helper[0][1] >= 4):
            collect()
        while held and not (in_helper and held[0] is in_helper[0][0]):
            yield tuple(held.popleft())
        t_last = time.perf_counter()
    while in_helper:
        collect()
    while held:
        yield tuple(held.popleft())


class DetectionAhead:
    """The detector over a bag's images on a second reader, in a thread, ahead of the pipeline.

    Iterating gives ``(frame, detections or None when not detected, seconds)`` in image order; the
    queue between the thread and the pipeline is bounded, so memory stays bounded. An error in the
    thread is raised in the iterating one."""

    _END = object()

    def __init__(self, open_reader: Callable[[], BagReader], detector, dope_every: int = 1, maxsize: int = 16,
                 keyframes=None):
        self._open, self._detector, self._every = open_reader, detector, dope_every
        self.gate = keyframe_gate(keyframes)
        self._queue: queue.Queue = queue.Queue(maxsize)
        self._stop = threading.Event()
        self.read_seconds = 0.0
        self.reader: BagReader | None = None  # the second reader, for its bad messages and skipped chunks
        self._thread = threading.Thread(target=self._run, name="replay-detection", daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.2)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        try:
            reader = self.reader = self._open()
            try:
                for frame, dets, reading, seconds in detected_images(reader, self._detector, self._every, self.gate):
                    self.read_seconds += reading
                    if not self._put((frame, dets, seconds)):
                        return
            finally:
                reader.close()
            self._put(self._END)
        except BaseException as exc:  # re-raised where the items are taken
            self._put(exc)

    def __iter__(self):
        while True:
            item = self._queue.get()
            if item is self._END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=30)


def detection_process(bag_path, topics: BagTopics, input_mode: str, kwargs: dict | None, dope_every: int,
                      keyframes, colour: bool = True):
    """Replay's detector side, ahead of the pipeline, in a child process of its own
    (:class:`testbed.replay_detection.DetectionReaderProcess`; its ``camera(info)`` still to be
    called) for the DOPE detector of ``kwargs`` (:func:`testbed.run.detector_kwargs`; the child builds
    it), unless ``kwargs`` is None or ``DOPESLAM_DETECTOR_PROCESS=0``; else None, and a thread
    (:class:`DetectionAhead`) runs a detector built here. The same images, detections and counts
    either way.

    Where the detector runs on every image (no keyframe gate, ``dope_every`` 1) it is the longest
    path, and a second process detects every other image (``DOPESLAM_DETECTOR_PROCESS`` ``1`` or
    ``2`` says how many; docs/speed.md). ``colour``: False where nothing reads the colour images' pixels
    (depth input, no loop closer, no live view): the child reads them for their stamps only."""
    from testbed.settings import detection_process_wanted, detector_processes_setting

    if kwargs is None or not detection_process_wanted():
        return None
    from stack.config import torch_threads
    from testbed.replay_detection import DetectionReaderProcess

    processes = detector_processes_setting()
    if processes is None:
        processes = 2 if dope_every <= 1 and keyframe_gate(keyframes) is None else 1
    threads = torch_threads() or (1 if processes == 2 else REPLAY_DETECTOR_THREADS.get(input_mode))
    return DetectionReaderProcess(bag_path, topics, input_mode, kwargs, None, dope_every, keyframes, threads=threads,
                                  helper=processes == 2, colour=colour)


# torch threads of replay's one detector process unless DOPESLAM_TORCH_THREADS says: one for colour
# input (as fast as two on two cores, for less CPU); torch's own count for depth input, whose several
# windows per image make the network the longest path (docs/speed.md); two processes take one each
REPLAY_DETECTOR_THREADS = {"rgb": 1, "depth": None}


def _merged(sensors, images):
    """Scans and wheel odometry (``sensors``) and detected images (``images``) in stamp order; at one
    stamp the sensor message first."""
    return heapq.merge(((m.stamp, 0, m, None) for m in sensors),
                       ((f.stamp, 1, f, (dets, s)) for f, dets, s in images), key=lambda x: (x[0], x[1]))


def _with_true_poses(images, bag: BagReader):
    """The detector process's frames with their true camera pose from ``bag``'s ground truth, as the
    pipeline's reader gives its own (the process's reader leaves the ground truth unread)."""
    for frame, dets, seconds in images:
        if frame.T_world_camera is None:
            frame.T_world_camera = bag.true_camera_pose(frame.stamp)
        yield frame, dets, seconds


def open_bag(path, topics: BagTopics, input_mode: str, need_camera: bool = True,
             ground_truth: bool = True, colour_pixels: bool = True) -> BagReader:
    """The bag on a reader of its own; ``ground_truth`` False: a reader for the detector side only,
    which leaves the ground truth (scored by the pipeline's reader) unread; ``colour_pixels`` False:
    the colour images are read for their stamps only (``BagReader``)."""
    extra = {"base_frame": topics.base_frame} if topics.base_frame else {}
    bag = BagReader(path, lidar_topic=topics.lidar, rgb_topic=topics.rgb, depth_topic=topics.depth,
                    camera_info_topic=topics.camera_info, require_camera=need_camera,
                    T_base_lidar=topics.T_base_lidar, T_base_camera=topics.T_base_camera,
                    max_bad_messages=topics.max_bad_messages, ground_truth=ground_truth,
                    colour_pixels=colour_pixels, **extra).open()
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
               vocabulary=None, odometry=None, odometry_only: bool = False, odometry_config=None,
               keyframes=None, detector_config=None) -> dict:
    """Run the stack's pipeline over a bag; returns the report (written to OUT/report.json).

    ``detector``: any :class:`stack.interfaces.Detector` (default: DOPE + FPR for ``input_mode``,
    ``stages``, ``fpr``, ``weights``, or as ``detector_config``, a :class:`stack.config.DetectorConfig`,
    says; where it runs in a child process, only the child builds it: the report's ``_detector``
    names what ran, for the outputs' provenance). ``odometry``: an :class:`stack.interfaces.Odometry`, or a
    name for :func:`stack.interfaces.load_odometry` (default: KISS-ICP, with ``odometry_config``, a
    :class:`stack.lidar_slam.LidarOdometryConfig`, or the defaults). ``parallel``: the detector
    runs on a second reader ahead of the pipeline, in a child process or a thread
    (:func:`detection_process`; else in the message loop).
    ``loop_closure``: the loop closer rides along (key frames from the colour images, scans); the
    corrected trajectory then places the labels, and replaces the odometry's in the outputs (the
    odometry-only ATE is reported beside it when the bag has ground truth). ``odometry_only``: the
    LiDAR (and wheel odometry) only: no images are read and no detector runs; the trajectory, the
    LiDAR map and an empty object store come out. ``keyframes``: a
    :class:`stack.keyframes.KeyframeSettings`: the detector runs only on images the robot moved or
    turned enough for (by the bag's wheel odometry), or after a while."""
    from sim.objects import load_catalog
    from testbed.run import detector_kwargs, detector_name, made_from, make_detector, make_odometry

    topics = topics or BagTopics()
    out = Path(out_dir)
    if results_bag is not None:  # never over the input, whatever --force says
        check_new_output(results_bag, "--results-bag", force=True, inputs=[bag_path])
    if write_outputs and (out.resolve() == Path(bag_path).resolve() or Path(bag_path).resolve() in out.resolve().parents):
        raise OutputError(f"--out {out}: is, or lies inside, the input bag {bag_path}; choose another folder")
    kept = edited_objects(out) if write_outputs else []  # checked before any work starts
    wall0 = time.perf_counter()
    # the detector's process first, where it runs in one: it builds its detector and opens the bag while
    # this process opens it (and builds none)
    dope = made_from(detector) if detector is not None else \
        detector_kwargs(input_mode, stages, fpr, weights, detector_config)
    # DOPE on depth reads no colour pixels (the detector's own input, whatever --input says); the loop
    # closer and live views do
    from testbed.progress import views_active

    colour = dope is None or dope.get("input", "rgb") != "depth" or loop_closure or views_active()
    ahead = detection_process(bag_path, topics, input_mode, dope, dope_every, keyframes, colour) \
        if parallel and not odometry_only else None
    try:
        bag = open_bag(bag_path, topics, input_mode, need_camera=not odometry_only)
    except BaseException:
        if ahead is not None:
            ahead.close()
        raise
    if odometry_only:
        parallel, loop_closure = False, False
    try:
        log.info("%s", bag.describe())
        if odometry_only:
            detector = None
        elif detector is None and ahead is None:  # the DOPE detector runs in this process
            detector = make_detector(input_mode, stages, fpr, weights, config=detector_config)
        if detector is not None and not isinstance(detector, Detector):  # in parallel the pipeline does not see it
            raise TypeError(f"detector {type(detector).__name__} has no detect(frame) method")
        dims = {c: s.dims for c, s in load_catalog().items()}
        truth = BagImageTruth(bag) if bag.topics.get(T.GT_IMAGE_OBJECTS) == "std_msgs/msg/String" else None
        odom = make_odometry(odometry, bag.T_base_velodyne, odometry_config) \
            if odometry is None or isinstance(odometry, str) else odometry

        lc = None
        if loop_closure:
            from testbed.loop_closing import LoopClosingRun

            lc = LoopClosingRun(vocabulary)
            if bag.rgb_topic is None:
                log.warning("%s: no colour images: the loop closer uses LiDAR key frames only", bag.path)

        pipe = DopeSlam(odom, None if parallel else detector, bag.T_base_camera, dims, policy, loop_closer=lc,
                        detect_every=dope_every, keep_observations=keep_detections,
                        keyframes=None if parallel else keyframes)  # in parallel the detection thread gates
        dlog = DetectionLog()
        unscored_frames = 0  # detected images whose per-image truth is missing (lost with a damaged chunk)
        all_dets: list = []
        scans = 0
        read_s = 0.0
        if parallel:
            if ahead is not None:
                ahead.camera(bag.camera_info)
                images = _with_true_poses(ahead, bag)
            else:
                ahead = DetectionAhead(lambda: open_bag(bag_path, topics, input_mode), detector,
                                       dope_every, keyframes=keyframes)
                images = ahead
            stream = _merged(bag.frames(lidar=True, camera=False, odometry=True), images)
        else:
            stream = ((m.stamp, 0, m, None) for m in bag.frames(lidar=True, camera=not odometry_only, odometry=True))
        from testbed.progress import EpisodeWatch  # progress bar (scans) and live views (--view)

        watch = EpisodeWatch(bag.path.name, bag.message_counts.get(bag.lidar_topic, 0), truth=bag.groundtruth,
                             pipe=pipe, unit="scans")
        t_last = time.perf_counter()
        for _, _, msg, given in stream:
            read_s += time.perf_counter() - t_last
            if isinstance(msg, CameraFrame):
                if given is not None:
                    dets, seconds = given
                    dets = pipe.on_image(msg) if dets is None else pipe.on_image(msg, dets)
                    dlog.seconds += seconds
                else:
                    dets = pipe.on_image(msg)
                if dets is not None:
                    dlog.frames += 1
                    truths = truth.get(msg) if truth is not None else None
                    if truths is not None:
                        flags = score_detections(dlog, dets, truths)
                    else:
                        unscored_frames += truth is not None
                        dlog.predictions += sum(d.fpr_pass for d in dets)
                        flags = None
                    if keep_detections:
                        all_dets.extend(dets if flags is None else zip(dets, flags))
                watch.image(msg, dets, flags if dets is not None else None)
            else:
                pose = pipe.on_message(msg)
                if isinstance(msg, LidarScan):
                    scans += 1
                    watch.scan(msg, pose)
                    watch.tick(scans, images=pipe.images, objects=len(pipe.store))
                    if scans % 100 == 0 and not watch.shown:
                        log.info("t = %.1f s: %d scans, %d images, %d map objects", msg.stamp, scans,
                                 pipe.images, len(pipe.store))
            t_last = time.perf_counter()
        if not parallel:
            dlog.seconds = pipe.timing["detection"]
        if not len(check_trajectory(odom, odom.trajectory())[0]):
            raise MissingTopicError(bag.path, "lidar", f"scans on {bag.lidar_topic} that odometry can register",
                                    bag.topics, f"{scans} scan(s) read, none registered")
        result = pipe.finish()
        store, stamps, poses, poses_odom = result.store, result.stamps, result.T_map_base, result.T_map_base_odometry
        map_points = result.map_points
        wall = time.perf_counter() - wall0

        gt = bag.groundtruth
        span = _bag_span(bag, stamps)
        meta = bag.metadata
        ran = detector if detector is not None else getattr(ahead, "built", None)  # built here, or in the process
        report: dict = {
            "bag": str(bag.path), "source": meta.get("source", "rosbag"),
            "scenario": meta.get("scenario", bag.path.stem), "seed": meta.get("seed"), "light": meta.get("light"),
            "input": input_mode, "stages": stages, "fpr": fpr, "policy": policy,
            "topics": {"lidar": bag.lidar_topic, "rgb": bag.rgb_topic, "depth": bag.depth_topic,
                       "camera_info": bag.camera_info_topic, "odometry": bag.odom_topic},
            "ground_truth": {"trajectory": gt is not None, "objects": bool(gt is not None and gt.objects),
                             "images": truth is not None},
            "bag_seconds": span, "wall_seconds": wall, "real_time_factor": span / wall if wall > 0 else None,
            "parallel_passes": parallel, "detector_process": ahead is not None and not isinstance(ahead, DetectionAhead),
            "detector_processes": 0 if ahead is None or isinstance(ahead, DetectionAhead) else 1 + ahead.helper,
            "detector": "none" if ran is None else detector_name(ran),
            "network_precision": getattr(ran, "precision", None),
            "network_refinement_order": getattr(ran, "refinement_order", None),
            "odometry_class": detector_name(odom), "odometry_only": odometry_only,
            "time_split_s": {"odometry": pipe.timing["odometry"], "odometry_reading": read_s,
                             "dope": dlog.seconds, "image_reading": ahead.read_seconds if ahead else 0.0,
                             "fusion": pipe.timing["fusion"]},
        }
        readers = [bag] + ([ahead.reader] if ahead is not None and ahead.reader is not None else [])
        salvaged = list(dict.fromkeys(r.salvaged for r in readers if r.salvaged))
        if salvaged:
            report["salvaged"] = "; ".join(salvaged)
        skipped = _skipped_chunks(readers)
        if skipped:  # damaged chunks passed over (by either reader): where, why, and what was lost
            report["skipped_chunks"] = skipped
        bad = _bad_messages(readers)
        if bad:  # skipped, counted and named; the detection reader's topics with the others
            report["bad_messages"] = bad
        gaps = _ground_truth_gaps(skipped)
        stats = getattr(odom, "stats", None)
        odometry = {"poses": int(len(stamps)), "scans": scans, "path_length_m": _path_length(poses),
                    "odometry_hz": getattr(stats, "hz", None)}
        T_world_map = None
        if gt is not None:
            scored = ~_in_spans(stamps, gaps)  # poses whose ground truth was lost are not scored
            T_world_map = _aligned(gt, stamps, poses, scored)
            if scored.sum() >= 2:
                odometry = {**score_trajectory(stamps[scored], poses[scored], gt, T_world_map), **odometry}
            if gaps:
                odometry["poses_unscored"] = int((~scored).sum())
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
        ws, wp = result.wheel_stamps, result.T_odom_base
        if gt is not None and len(ws) > 1:
            keep = ~_in_spans(ws, gaps)
            if keep.sum() > 1:
                report["wheel_odometry"] = score_trajectory(np.asarray(ws)[keep], np.asarray(wp)[keep], gt,
                                                            _aligned(gt, ws, wp, keep))
        dsum = dlog.summary()
        if truth is None:  # precision and recall need the truth per image: left out
            dsum = {k: dsum[k] for k in ("frames", "predictions", "fps")}
        dsum["detections_without_pose"] = result.unposed
        if truth is not None and unscored_frames:
            dsum["frames_without_ground_truth"] = unscored_frames
        gate = ahead.gate if ahead is not None else pipe.keyframes
        if gate is not None:  # images the keyframe gate kept from the detector
            dsum["keyframe_held_images"] = gate.held
        report["detection"] = dsum
        if gt is not None and gt.objects:
            labels, labels_summary = score_labels(store, gt.objects, T_world_map)
            report["labels"], report["labels_summary"] = labels, labels_summary
            watch.finish(store, T_world_map, labels_summary.get("map_labels"))
            report["candidates"] = candidate_rows(store, T_world_map)
        else:
            report["labels"] = [{"id": m.id, "class": m.cls, "label_xyz_map": [float(v) for v in m.xyz],
                                 "observations": m.observations, "status": m.status, "reason": m.reason}
                                for m in store]
            watch.finish(store, T_world_map)
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
                        _map_png(stage / "map.png", shim, T_world_map, poses, map_points, report["labels"], report)
                    else:
                        _map_png_untruthed(stage / "map.png", poses, map_points, store, report, T_world_map)
                else:
                    write_tum(stage / "estimate_tum.txt", stamps, poses)
                    _map_png_untruthed(stage / "map.png", poses, map_points, store, report)
                write_results_bag(results_bag or stage / RESULTS_BAG_NAME, store, map_points, stamps, poses,
                                  T_world_map=T_world_map, objects=gt.objects if gt is not None and gt.objects else None)
                write_json(stage / "report.json", report)
        if keep_detections:
            report["_detections"] = all_dets
            report["_store"] = store
            report["_observations"] = result.observations
            report["_trajectory"] = (stamps, poses)
            report["_T_world_map"] = T_world_map
        report["_detector"] = ran
        return report
    finally:
        if ahead is not None:
            ahead.close()
        bag.close()


def _skipped_chunks(readers: list[BagReader]) -> list[dict]:
    """The damaged chunks any of the readers passed over, each once, in file order."""
    seen: dict[tuple, dict] = {}
    for reader in readers:
        for chunk in reader.skipped_chunks:
            seen.setdefault((chunk["file"], chunk["byte"]), chunk)
    return [seen[k] for k in sorted(seen)]


def _bad_messages(readers: list[BagReader]) -> dict[str, dict]:
    """The readers' bad-message summaries as one (the two readers of a replay read different topics;
    a topic both read is counted once, by the reader that met more)."""
    out: dict[str, dict] = {}
    for reader in readers:
        for topic, entry in reader.bad_message_summary().items():
            if topic not in out or entry["count"] > out[topic]["count"]:
                out[topic] = entry
    return dict(sorted(out.items()))


def _ground_truth_gaps(skipped: list[dict]) -> list[tuple[float, float]]:
    """Bag-time spans whose ground-truth poses were lost with a skipped chunk."""
    return [(c["start_s"], c["end_s"]) for c in skipped
            if "start_s" in c and c.get("messages", {}).get(T.GT_BASE_POSE)]


def _aligned(gt, stamps, poses, scored: np.ndarray) -> np.ndarray:
    """T_world_frame from the ground truth at the first pose (the frame's origin); when that pose's
    ground truth was lost, at the first scored pose instead."""
    if not scored.size or scored[0] or not scored.any():
        return gt.T_world_base_at(stamps[0])
    k = int(np.argmax(scored))
    return gt.T_world_base_at(stamps[k]) @ np.linalg.inv(np.asarray(poses[k]))


def _in_spans(stamps: np.ndarray, spans: list[tuple[float, float]]) -> np.ndarray:
    stamps = np.asarray(stamps, dtype=float)
    out = np.zeros(stamps.shape, dtype=bool)
    for a, b in spans:
        out |= (stamps >= a) & (stamps <= b)
    return out


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
