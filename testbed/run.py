"""``dopeslam run``: the main job. The simulator is the message source; the stack's pipeline
(:class:`stack.pipeline.DopeSlam`) gets the frames in time order, as on a robot: LiDAR -> odometry;
images -> DOPE -> FPR -> fusion (HTM chain at the image's time) -> object store. Then everything is
scored against the simulator's ground truth: each image's detections as the pipeline returns them,
the trajectory and the map at the end.

Images wait until the odometry has a pose after their timestamp (the next LiDAR sweep), so each is
fused with an interpolated pose, never an extrapolated one (except at the very end of the episode):
the pipeline's rule, see ``stack/pipeline.py``.
"""
from __future__ import annotations

import contextlib
import logging
import math
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from stack.config import torch_threads
from stack.errors import InputDataError
from stack.interfaces import detect
from stack.lidar_slam import LidarOdometry
from stack.messages import CameraFrame, Detection, LidarScan, WheelOdometry
from stack.metrics import ate_rmse, ate_rmse_umeyama, rpe, write_tum
from stack.object_store import ObjectStore
from stack.pipeline import DopeSlam
from stack.transforms import transform_points
from testbed.detection_process import detector_name
from testbed.scoring import score_map, summary_line
from testbed.io import edited_objects, output_dir, write_json

log = logging.getLogger(__name__)

FALSE_POSITIVE_M = 0.05  # a detection off by more than this in any axis (camera frame) is a false positive (paper)
INSTANCE_RANGE_M = (0.3, 1.5)  # an object counts as an instance to detect when this near ...
INSTANCE_VISIBLE = 0.5  # ... and at least this much of it is visible


@dataclass
class DetectionLog:
    frames: int = 0
    predictions: int = 0
    false_positives: int = 0
    instances: int = 0
    correct: int = 0
    seconds: float = 0.0
    rows: list = field(default_factory=list)  # per detection: stamp, cls, fpr, belief_sum, error
    instances_scored: bool = True  # False: images without segmentation, so no instances and no recall

    def summary(self) -> dict:
        tp = self.predictions
        scored = self.instances_scored
        return {"frames": self.frames, "predictions": tp, "false_positives": self.false_positives,
                "instances": self.instances if scored else None, "correct": self.correct if scored else None,
                "precision": (tp - self.false_positives) / tp if tp else None,
                "recall": self.correct / self.instances if scored and self.instances else None,
                "fps": self.frames / self.seconds if self.seconds > 0 else None,
                "false_positive_threshold_m": FALSE_POSITIVE_M,
                "instance_definition": f"object {INSTANCE_RANGE_M[0]}-{INSTANCE_RANGE_M[1]} m away, "
                                       f">= {INSTANCE_VISIBLE:.0%} visible"}


def score_detections(dlog: DetectionLog, detections: list[Detection], truths: list[dict]) -> list[bool]:
    """Count predictions, false positives (> 5 cm in any camera axis from the truth of that class)
    and instances; returns per detection whether it is correct."""
    correct_flags = []
    seen_correct = set()
    for det in detections:
        cands = [t for t in truths if t["cls"] == det.cls and t["in_front"]]
        err = min((np.abs(det.T_cam_obj[:3, 3] - t["T_cam_obj"][:3, 3]).max() for t in cands), default=np.inf)
        ok = bool(err <= FALSE_POSITIVE_M)
        dlog.rows.append({"stamp": det.stamp, "cls": det.cls, "fpr_pass": det.fpr_pass,
                          "belief_sum": det.belief_sum, "max_axis_error_m": float(err)})
        if det.fpr_pass:
            dlog.predictions += 1
            if not ok:
                dlog.false_positives += 1
            elif det.cls not in seen_correct:
                seen_correct.add(det.cls)
        correct_flags.append(ok)
    for t in truths:
        if t["visible_fraction"] is None:  # no segmentation rendered (the fast profile): recall not scored
            dlog.instances_scored = False
            continue
        if t["in_front"] and INSTANCE_RANGE_M[0] <= t["distance_m"] <= INSTANCE_RANGE_M[1] \
                and t["visible_fraction"] >= INSTANCE_VISIBLE:
            dlog.instances += 1
            if t["cls"] in seen_correct:
                dlog.correct += 1
    return correct_flags


def score_labels(store: ObjectStore, objects, T_world_map: np.ndarray) -> tuple[list[dict], dict]:
    """The whole map scored (``testbed.scoring``): per object rows; the summary also holds the
    per-label rows under ``map_labels``."""
    rows, map_rows, summary = score_map(store.labels(), objects, T_world_map, len(store.candidates()))
    return rows, {**summary, "map_labels": map_rows}


def candidate_rows(store: ObjectStore, T_world_map: np.ndarray) -> list[dict]:
    """The objects the stack kept but did not publish, in world, with the reason."""
    return [{"id": m.id, "class": m.cls, "xyz": [float(v) for v in transform_points(T_world_map, m.xyz[None])[0]],
             "observations": m.observations, "reason": m.reason} for m in store.candidates()]


def score_trajectory(stamps, T_map_base, ep, T_world_map) -> dict:
    gt = ep.T_world_base_at(stamps)
    est = T_world_map @ T_map_base
    r = rpe(est, gt)
    return {"ate_rmse_m": ate_rmse(est, gt), "ate_rmse_umeyama_m": ate_rmse_umeyama(est, gt),
            "rpe_trans_pct": r.trans_pct, "rpe_rot_deg_per_m": r.rot_deg_per_m, "poses": int(len(stamps))}


def detector_kwargs(input_mode: str, stages: int, fpr: bool, weights=None, config=None) -> dict:
    """``stack.dope_fpr.DopeDetector``'s keyword arguments (``dims``, ``threads`` aside) for
    :func:`make_detector`'s arguments; plain values (paths as strings)."""
    kw = config.dope_kwargs() if config is not None else \
        {"weights": weights, "input": input_mode, "stages": stages, "fpr": fpr}
    return {k: str(v) if isinstance(v, Path) else v for k, v in kw.items()}


def make_detector(input_mode: str, stages: int, fpr: bool, weights=None, config=None, threads: int | None = None):
    """DOPE + FPR for the simulator's classes; ``config`` (a ``stack.config.DetectorConfig``), when
    given, sets everything (the other arguments are then ignored). ``threads``: torch threads when
    ``DOPESLAM_TORCH_THREADS`` is unset (None: torch's default)."""
    from testbed.detection_process import build_detector

    kwargs = detector_kwargs(input_mode, stages, fpr, weights, config)
    detector = build_detector(kwargs, torch_threads() or threads)
    _MADE[detector] = kwargs
    return detector


_MADE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # detector -> the kwargs make_detector built it from


def made_from(detector) -> dict | None:
    """The :func:`detector_kwargs` a detector was made from by :func:`make_detector` (a child process
    can build its twin from them), or None for any other detector."""
    try:
        return _MADE.get(detector)
    except TypeError:  # not weakly referenceable: not one make_detector made
        return None


def ahead_settings(sequential: bool, detector, images: int | None = None) -> tuple[bool, bool]:
    """Whether ``run_episode`` may run ``detector`` ahead of the pipeline, and its render worker then.

    Ahead, three things share the two cores of the reference machine: the simulator with the stack's
    odometry and fusion, the camera's renderer in a second process (``sim.render.RenderWorker``) and the
    DOPE detector with one torch thread, in a child process of its own (``testbed.detection_process``;
    a thread for other detectors). On two idle cores that took the default episode from 132 s (in the
    loop, torch's two threads, no render worker) to 101 s with the same bytes out (docs/speed.md).
    The render worker: ``DOPESLAM_RENDER_WORKER`` when set, else on when ahead and the episode renders
    at least :data:`HELPERS_FROM_IMAGES` images (``images``; None: as many as it likes): a
    shorter one spends more on the worker's start-up than the worker saves it."""
    from sim.render import render_worker_wanted

    ahead = not sequential and not callable(getattr(detector, "bind_episode", None))
    return ahead, render_worker_wanted(ahead and (images is None or images >= HELPERS_FROM_IMAGES))


# Helper processes pay for themselves only in episodes long enough. Each costs its start-up (Python,
# then torch and the network or PyBullet and the world: 3-4 CPU s) and, while it runs, the cores it
# shares with the others. On two cores (docs/speed.md, "Helper processes for long episodes only"),
# episodes of up to 100 images ran in less time and CPU with neither a render process nor a second
# detector process; from about 150 on the two gain or break even.
HELPERS_FROM_IMAGES = 150


def episode_images(duration, rate) -> int | None:
    """About how many images the camera takes in ``duration`` s at ``rate`` Hz (one at the start); None
    for values the episode itself will refuse."""
    try:
        n = float(duration) * float(rate)
    except (TypeError, ValueError):
        return None
    return int(n) + 1 if math.isfinite(n) and n >= 0 else None


DOPE_DETECTOR = "stack.dope_fpr:DopeDetector"


def detector_processes_wanted(every: int = 1, keyframes=None, images: int | None = None) -> int:
    """How many detector processes ``dopeslam run`` starts ahead of the pipeline for its DOPE
    detector: ``DOPESLAM_DETECTOR_PROCESS`` ``1`` or ``2`` when set; else two where every image is
    detected (the network is then the run's longest path: the two detect the images in turn) and
    there are at least :data:`HELPERS_FROM_IMAGES` of them (``images``, the camera's; None: as
    many as it likes), one where some go undetected (a keyframe gate, ``every`` over 1) or the
    episode is shorter. The same bytes either way (docs/speed.md)."""
    from testbed.settings import detector_processes_setting

    chosen = detector_processes_setting()
    if chosen is not None:
        return chosen
    if _CameraDemand.useful(every, keyframes) or (images is not None and images < HELPERS_FROM_IMAGES):
        return 1
    return 2


def odometry_process_wanted(odometry, every: int = 1, keyframes=None) -> bool:
    """Whether ``dopeslam run``'s KISS-ICP registers in a child process of its own
    (:mod:`testbed.odometry_process`) where the detector runs ahead without a loop closer: for the
    default odometry (``odometry`` None or its name), without live views (which read every sweep's
    registered points), where some images go undetected (``every`` over 1 or a keyframe gate: with
    every image detected both cores are already busy and the extra process only costs time,
    docs/speed.md). ``DOPESLAM_ODOMETRY_PROCESS=0`` never, ``=1`` whatever the schedule. The same
    bytes either way."""
    from stack.interfaces import DEFAULT_ODOMETRY
    from testbed.progress import views_active
    from testbed.settings import odometry_process_wanted as wanted

    if not (odometry is None or odometry == DEFAULT_ODOMETRY) or views_active():
        return False
    asked = wanted()
    return _CameraDemand.useful(every, keyframes) if asked is None else asked


def make_odometry(odometry, T_base_lidar: np.ndarray, kiss_icp_config=None):
    """The pipeline's odometry: None or ``kiss-icp``: KISS-ICP with ``kiss_icp_config`` (a
    ``stack.lidar_slam.LidarOdometryConfig``); another name: :func:`stack.interfaces.load_odometry`;
    a callable: called with ``T_base_lidar``. Raises ``stack.interfaces.ImportPathError``."""
    from stack.interfaces import DEFAULT_ODOMETRY, load_odometry

    if odometry is None or odometry == DEFAULT_ODOMETRY:
        return LidarOdometry(T_base_lidar, kiss_icp_config)
    if isinstance(odometry, str):
        return load_odometry(odometry, T_base_lidar)
    return odometry(np.asarray(T_base_lidar, dtype=float))


class _Schedule:
    """Which images the detector ahead runs on: every ``every``-th image that the keyframe gate (of
    ``keyframes``; None: none) passes, fed the wheel odometry in the order the messages come. One
    rule for :class:`_Ahead` and :class:`_CameraDemand`, so both pick the same images."""

    def __init__(self, every: int, keyframes):
        from stack.keyframes import keyframe_gate

        self.every, self.gate, self._images = max(1, int(every)), keyframe_gate(keyframes), 0

    def see(self, msg) -> None:
        if self.gate is not None and isinstance(msg, WheelOdometry):
            self.gate.on_wheel_odometry(msg)

    def runs_on(self, frame) -> bool:
        """Whether the detector runs on ``frame`` (anything with a ``stamp``), the next image in order."""
        run = self._images % self.every == 0 and (self.gate is None or self.gate.passes(frame))
        self._images += 1
        return run


class _CameraDemand(_Schedule):
    """Which camera frames the detector running ahead will look at, decided as the simulator makes
    them (:attr:`sim.episode.Episode.camera_demand`): its own :class:`_Schedule`, shown the same
    messages in the same order as :class:`_Ahead`'s, so it wants exactly the images that one
    detects. The rest are not rendered."""

    @staticmethod
    def useful(every: int, keyframes) -> bool:
        """Whether any image goes undetected (a keyframe gate, or ``every`` over 1)."""
        from stack.keyframes import keyframe_gate

        return int(every) > 1 or keyframe_gate(keyframes) is not None

    def wants(self, t: float) -> bool:
        return self.runs_on(SimpleNamespace(stamp=t))


class _Ahead:
    """The detector in a thread, ahead of the pipeline: the simulator renders the next images while
    the network works on this one (the network's kernels release the GIL). Iterating gives
    ``(message, detections or None, seconds)`` in the simulator's order; detections are those of
    every ``every``-th image (None for the rest and for other messages), exactly what the pipeline's
    own call would have found, so the pipeline's results are the same bytes either way."""

    def __init__(self, messages, detector, every: int = 1, images_ahead: int = 2, processes=(), keyframes=None,
                 odometry=None, scans_ahead: int = 4):
        """``processes``: :class:`testbed.detection_process.DetectionProcess` objects that run
        ``detector``'s twin in child processes and detect the images in turn (none: a thread; the
        caller closes them). ``keyframes``: the pipeline's
        :class:`stack.keyframes.KeyframeSettings`; a gate of its own, fed the same messages in the same
        order, passes the same images as the pipeline's. ``odometry``: a
        :class:`testbed.odometry_process.OdometryProcess` whose follower is the pipeline's odometry:
        each sweep is handed to it as the simulator makes it, and its result is fed to the follower
        before the sweep is given out (the caller closes it). At most ``images_ahead`` images per
        detector process (or thread) and ``scans_ahead`` sweeps wait ahead of the pipeline."""
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        self._messages, self._detector = messages, detector
        self._processes = list(processes)
        self._ahead = max(1, int(images_ahead)) * max(1, len(self._processes))
        self._scans_ahead = max(1, int(scans_ahead))
        self._submitted = 0  # images handed to the detector processes, in turn
        self._odometry = odometry
        self._pool = None if self._processes else \
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="run-detection")
        self._queue: deque = deque()
        self._schedule = _Schedule(every, keyframes)
        self.wait_seconds = 0.0  # the pipeline's wait for a detection or a registration (not simulation time)

    @property
    def gate(self):
        """The keyframe gate that decides which images are detected (None without one)."""
        return self._schedule.gate

    def _detect(self, frame):
        t0 = time.perf_counter()
        dets = detect(self._detector, frame)
        return dets, time.perf_counter() - t0

    def __iter__(self):
        pending = {CameraFrame: 0, LidarScan: 0}  # images and sweeps in the queue
        try:
            for msg in self._messages:
                job = None
                self._schedule.see(msg)
                if isinstance(msg, CameraFrame):
                    if self._schedule.runs_on(msg):
                        if msg.extra.get("unrendered"):  # the camera demand and this schedule disagree: a bug
                            raise RuntimeError(f"image at {msg.stamp:.6f} s: to be detected, but not rendered")
                        if self._processes:  # in turn: each process answers its own images in order
                            job = self._processes[self._submitted % len(self._processes)].submit(msg)
                            self._submitted += 1
                        else:
                            job = self._pool.submit(self._detect, msg)
                    pending[CameraFrame] += 1
                elif isinstance(msg, LidarScan):
                    if self._odometry is not None:
                        self._odometry.submit(msg)
                    pending[LidarScan] += 1
                self._queue.append((msg, job))
                while pending[CameraFrame] > self._ahead or pending[LidarScan] > self._scans_ahead:
                    kind = self._take()
                    if kind in pending:
                        pending[kind] -= 1
                    yield self._last
            while self._queue:
                self._take()
                yield self._last
        finally:
            for _, job in self._queue:
                if job is not None:
                    job.cancel()
            if self._pool is not None:
                self._pool.shutdown(wait=True)

    def _take(self) -> type | None:
        """The oldest message, made ready for the pipeline (its detections, its registration), into
        ``_last``; returns its type."""
        msg, job = self._queue.popleft()
        if job is None:
            self._last = (msg, None, 0.0)
            if self._odometry is not None and isinstance(msg, LidarScan):
                t0 = time.perf_counter()
                if self._odometry.take() is not msg:
                    raise RuntimeError(f"sweep at {msg.stamp:.6f} s: the odometry process answered another")
                self.wait_seconds += time.perf_counter() - t0
        else:
            t0 = time.perf_counter()
            dets, seconds = job.result()
            self.wait_seconds += time.perf_counter() - t0
            self._last = (msg, dets, seconds)
        return CameraFrame if isinstance(msg, CameraFrame) else LidarScan if isinstance(msg, LidarScan) else None


def run_episode(scenario=None, out_dir="out/run", seed=None, light=None, input_mode="rgb", stages=6, fpr=True,
                policy="robust-mean", duration=None, weights=None, detector=None, dope_every: int = 1,
                write_outputs: bool = True, keep_detections: bool = False, bag_writer=None,
                results_bag=None, loop_closure: bool = False, config=None, faults=(), store=None, retire=True, odometry=None,
                profile: str | None = None, sequential: bool = False) -> dict:
    """One simulated episode through the stack's pipeline (:class:`stack.pipeline.DopeSlam`), scored.

    ``odometry``: None (KISS-ICP), a name for :func:`stack.interfaces.load_odometry` (``wheel``,
    ``MODULE:CLASS``, an entry point's name) or a callable ``T_base_lidar -> Odometry``.

    ``detector``: any :class:`stack.interfaces.Detector` (default: DOPE + FPR for ``input_mode``,
    ``stages``, ``fpr``, ``weights``); one with ``bind_episode(ep)`` is given the episode before the
    first frame (a detector that needs the simulator's truth, e.g. ``testbed.oracle_detector``).
    ``policy``: a registered labelling policy's name (``stack.interfaces.resolve_policy`` registers
    a ``MODULE:FUNCTION``). ``bag_writer``: an open ``testbed.bags.BagWriter`` that records the
    episode as it runs (``testbed/record.py``); ``results_bag``: where the results bag goes (default
    OUT/results_bag). ``loop_closure``: key frames and scans also go to a loop closer
    (``testbed/loop_closing.py``); at the end the trajectory is corrected and every fused detection
    is fused again with it. ``config``: a ``stack.config.StackConfig`` (or ``testbed.settings.RunConfig``)
    whose settings replace ``input_mode``, ``stages``, ``fpr``, ``weights``, ``dope_every`` and
    ``loop_closure`` and set the odometry, evidence, store and loop closure; it is written to
    OUT/config.toml and the report gets its ``provenance``. ``faults``: ``NAME=VALUE`` sensor faults
    over the scenario's ``[faults]`` (``sim.faults``); ``store``: an object store file (.xlsx/.json)
    to start from and save the updated map to; ``retire``: retire labels whose place is seen empty
    (True: ``config``'s ``[retire]`` settings, or ``stack.retire.RetireConfig()`` without a config; a
    ``RetireConfig``; or False); see ``testbed/dynamic.py``. ``profile``: ``full`` or ``fast``
    (``testbed.settings.profile_sensors``; None: ``config``'s ``run.profile``, else ``full``).
    ``sequential``: run the detector in the message loop; by default it runs in a thread a few images
    ahead of the pipeline, with the camera rendered in a second process and the DOPE detector made
    only in a child process with one torch thread, started before the world is built (two such
    processes, images in turn, where every image is detected: :func:`detector_processes_wanted`; in an
    episode of under :data:`HELPERS_FROM_IMAGES` images, one, and no render process)
    (:func:`ahead_settings`, ``DOPESLAM_DETECTOR_PROCESS``; the same results, less wall time), except in
    scenarios with events and with a detector bound to the episode, whose truth must be read at the
    image's own time, and while recording (``bag_writer``). Ahead, where not every image is detected
    (``dope_every`` over 1, a keyframe gate), the images the detector will not see are not rendered
    (:class:`_CameraDemand`; not with loop closure, faults or live views): the same results. There,
    KISS-ICP also registers the sweeps in a child process beside the simulator
    (:func:`odometry_process_wanted`; not with loop closure, another odometry or live views): the
    same results."""
    from sim.episode import Episode
    from sim.objects import load_catalog

    out = Path(out_dir)
    kept = edited_objects(out) if write_outputs else []  # checked before any work starts
    if config is not None:
        d = config.detector
        input_mode, stages, fpr, weights, dope_every = d.input, d.stages, d.fpr, d.weights, d.every
        loop_closure = config.loop_closure.enabled
        if retire is True:
            retire = config.retire.settings() or False
        _check_config(config)
    from sim.scenario import Scenario, load_scenario

    scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    if profile is None:
        profile = getattr(getattr(config, "run", None), "profile", "full")
    camera_rate, segmentation = None, True
    if profile != "full":
        from testbed.settings import profile_sensors

        needs = bag_writer is not None or callable(getattr(detector, "bind_episode", None)) \
            or any(e.kind == "walk" for e in scenario.events)
        camera_rate, segmentation = profile_sensors(profile, scenario.sensors.camera_rate, needs)
    images = episode_images(scenario.duration if duration is None else duration,
                            scenario.sensors.camera_rate if camera_rate is None else camera_rate) \
        if scenario.sensors.camera else 0
    # in the loop: with events, and while recording (the bag interleaves the ground truth by the loop)
    ahead_wanted, render_worker = ahead_settings(sequential or bool(scenario.events) or bag_writer is not None,
                                                 detector, images)
    in_process = None  # the camera of the detector process, where the DOPE detector runs in one
    if detector is None:
        from testbed.detection_process import build_detector
        from testbed.settings import detection_process_wanted

        own_kwargs = detector_kwargs(input_mode, stages, fpr, weights, None if config is None else config.detector)
        if ahead_wanted and detection_process_wanted() and scenario.sensors.camera:
            from sim.camera import default_camera_info

            in_process = default_camera_info(scenario.sensors.camera_width, scenario.sensors.camera_height)
        else:
            detector = build_detector(own_kwargs, torch_threads() or (1 if ahead_wanted else None))
    dims = {c: s.dims for c, s in load_catalog().items()}
    wall0 = time.perf_counter()
    lidar = getattr(getattr(config, "run", None), "lidar", None)
    closing = contextlib.ExitStack()
    keyframes = None if config is None else config.detector.keyframes()
    processes = []  # the detector's processes, where the DOPE detector runs in its own
    if in_process is not None:  # started first: it builds its network while the world is built here
        from testbed.detection_process import DetectionProcess

        processes = [DetectionProcess(own_kwargs, in_process, torch_threads() or 1, quiet=i > 0)
                     for i in range(detector_processes_wanted(dope_every, keyframes, images))]
        for p in processes:
            closing.callback(p.close)
    with closing, Episode(scenario, seed=seed, duration=duration, light=light, camera_rate=camera_rate,
                          segmentation=segmentation, render_worker=render_worker,
                          lidar_packets=None if lidar is None else lidar == "packets") as ep:
        recorder = None
        if bag_writer is not None:
            from testbed.record import EpisodeRecorder

            recorder = EpisodeRecorder(bag_writer, ep)
        if callable(getattr(detector, "bind_episode", None)):
            detector.bind_episode(ep)
        lc = None
        if loop_closure:
            from testbed.loop_closing import LoopClosingRun

            lc = LoopClosingRun() if config is None else \
                LoopClosingRun(config.loop_closure.vocabulary, config.loop_closure.closure_config())
        kiss = None  # KISS-ICP in a child process, beside the simulator (odometry_process_wanted)
        if ahead_wanted and lc is None and odometry_process_wanted(odometry, dope_every, keyframes):
            from stack.pipeline import MAP_EVERY
            from testbed.odometry_process import OdometryProcess

            kiss = OdometryProcess(ep.T_base_velodyne, None if config is None else config.odometry, MAP_EVERY)
            closing.callback(kiss.close)
            odom = kiss.odometry
        else:
            odom = make_odometry(odometry, ep.T_base_velodyne, None if config is None else config.odometry)
        pipe = DopeSlam(odom, detector, ep.T_base_camera, dims, policy, loop_closer=lc, detect_every=dope_every,
                        keep_observations=keep_detections, keyframes=keyframes)
        if config is not None:  # the store as configured (before the first message)
            pipe.store = ObjectStore(dims=dims, gate_m=config.store.gate_m, policy=policy,
                                     evidence=config.evidence_or_none())
        from stack.retire import RetireConfig
        from testbed.dynamic import DynamicRun

        dyn = DynamicRun(ep, pipe, faults, store, RetireConfig() if retire is True else (retire or None))
        dlog = DetectionLog()
        all_dets: list[tuple[Detection, bool]] = []
        simulation_s = 0.0
        t_last = time.perf_counter()
        last_log = t_last
        from testbed.progress import EpisodeWatch  # progress bar and live views (--view)

        watch = EpisodeWatch(f"{ep.sc.name} seed {ep.seed}", ep.duration, truth=ep, pipe=pipe)

        ahead = None
        if ahead_wanted:
            from testbed.progress import views_active

            # images the detector will not see are not rendered, where nothing else looks at them
            if _CameraDemand.useful(dope_every, keyframes) and lc is None and dyn.injector is None \
                    and not views_active():
                ep.camera_demand = _CameraDemand(dope_every, keyframes)
            ahead = _Ahead(dyn.messages(), detector, dope_every, processes=processes, keyframes=keyframes,
                           odometry=kiss)
        stream = ((m, None, 0.0) for m in dyn.messages()) if ahead is None else ahead
        for msg, found, found_s in stream:
            simulation_s += time.perf_counter() - t_last
            truths = None
            if isinstance(msg, CameraFrame):
                if ahead is None:
                    dets = pipe.on_image(msg)
                elif found is None:  # not an image the detector runs on (detect_every): the pipeline skips it too
                    dets = pipe.on_image(msg)
                else:
                    dets = pipe.on_image(msg, found)
                    pipe.timing["detection"] += found_s
                if dets is not None:  # scored here: the truth is the simulator's, not the stack's
                    dlog.frames += 1
                    truths = ep.image_truth(msg)
                    flags = score_detections(dlog, dets, truths)
                    dyn.on_image(msg, dets, flags, truths)
                    watch.image(msg, dets, flags)
                    if keep_detections:
                        all_dets.extend(zip(dets, flags))
            else:
                pose = pipe.on_message(msg)
                if isinstance(msg, LidarScan):
                    watch.scan(msg, pose)
            if recorder is not None:
                recorder.write(msg, truths)
            t_last = time.perf_counter()
            watch.tick(msg.stamp, images=dlog.frames, objects=len(pipe.store))
            if t_last - last_log > 15 and not watch.shown:  # the bar says it when shown
                last_log = t_last
                log.info("t = %5.1f s of %.0f s: %d scans, %d images, %d map objects", msg.stamp, ep.duration,
                         pipe.registered, dlog.frames, len(pipe.store))
        if ahead is not None:  # the wait for a detection was the network's time, not the simulator's
            simulation_s -= ahead.wait_seconds
        result = pipe.finish()
        if config is not None and lc is not None:  # loop closure placed the map again in a fresh store
            result.store.evidence = config.evidence_or_none()
            result.store.publish()
        dlog.seconds = pipe.timing["detection"]
        timing = {"simulation": simulation_s,
                  "odometry": pipe.timing["odometry"] if kiss is None else odom.stats.seconds,
                  "dope": pipe.timing["detection"],
                  "fusion": pipe.timing["fusion"]}
        if recorder is not None:
            recorder.finish()
            timing["recording"] = recorder.seconds
        wall = time.perf_counter() - wall0
        store, stamps, poses, map_points = result.store, result.stamps, result.T_map_base, result.map_points
        if not len(stamps):  # no map frame, so nothing to place or score
            fix = "its [sensors] has lidar = false" if not ep.sc.sensors.lidar else \
                "a longer --duration, fewer dropped scans, or an odometry that registers them"
            raise InputDataError(f"{ep.sc.name}: the odometry registered no LiDAR scan in {ep.duration:g} s, so "
                                 f"there is no map ({fix})")
        T_world_map = ep.T_world_base_at(stamps[0])  # map = base_link at the first registered scan
        odo = score_trajectory(stamps, poses, ep, T_world_map)
        if lc is not None:  # the closed-loop trajectory replaced the odometry's; labels were placed again
            odo.update(lc.summary(stamps, result.T_map_base_odometry, poses, T_world_map, ep.T_world_base_at))
        odo["odometry_hz"] = getattr(getattr(odom, "stats", None), "hz", None)
        T_world_odom0 = ep.T_world_base_at(result.wheel_stamps[0])
        wheel_score = score_trajectory(result.wheel_stamps, result.T_odom_base, ep, T_world_odom0)
        labels, labels_summary = score_labels(store, ep.objects, T_world_map)
        ran = processes[0].built() if processes else detector  # built here, or only in the detector process
        report = {
            "scenario": ep.sc.name, "seed": ep.seed, "light": ep.light, "profile": profile,
            "lidar": "packets" if ep.lidar_packets else "points",
            "camera_rate_hz": ep.camera_rate, "camera_frames_unrendered": ep.unrendered_frames,
            "input": input_mode, "stages": stages,
            "fpr": fpr, "policy": policy, "detector": detector_name(ran),
            "network_precision": getattr(ran, "precision", None),
            "network_refinement_order": getattr(ran, "refinement_order", None), "odometry_class": detector_name(odom),
            "odometry_process": kiss is not None, "detector_processes": len(processes),
            "render_processes": ep.render_processes,
            "sim_seconds": ep.sim_seconds, "wall_seconds": wall,
            "real_time_factor": ep.sim_seconds / wall, "time_split_s": timing,
            "odometry": odo, "wheel_odometry": wheel_score,
            "detection": {**dlog.summary(), "detections_without_pose": result.unposed},
            "labels": labels, "labels_summary": labels_summary,
            "candidates": candidate_rows(store, T_world_map),
            "map_floor": None if store.floor is None else {"normal": [float(v) for v in store.floor[0]],
                                                           "d_m": store.floor[1]},
        }
        gate = pipe.keyframes if ahead is None else ahead.gate  # where the detector runs ahead, its gate decides
        if gate is not None:  # images the keyframe gate kept from the detector
            report["detection"]["keyframe_held_images"] = gate.held
        dyn.report(report, store, T_world_map)
        watch.finish(store, T_world_map, labels_summary.get("map_labels"))
        if config is not None:
            from testbed.provenance import detector_files, provenance

            w, t = detector_files(ran)
            report["provenance"] = provenance(ep.seed, getattr(ep.sc, "source", None), w, t)
        if write_outputs:  # into a hidden sibling, renamed into place whole; report.json last
            with output_dir(out) as stage:
                store.keep_edited(kept)  # rows a person marked edited in the folder's store files
                if config is not None:
                    from stack.config import write_config

                    write_config(config, stage / "config.toml")
                dyn.save_store(store)
                store.save(stage / "labels.xlsx")
                store.save(stage / "labels.json")
                write_tum(stage / "estimate_tum.txt", stamps, T_world_map @ poses)
                write_tum(stage / "groundtruth_tum.txt", stamps, ep.T_world_base_at(stamps))
                _map_png(stage / "map.png", ep, T_world_map, poses, map_points, labels, report)
                from testbed.record import RESULTS_BAG_NAME, write_results_bag

                write_results_bag(results_bag or stage / RESULTS_BAG_NAME, store, map_points, stamps, poses,
                                  T_world_map=T_world_map, objects=ep.objects)
                write_json(stage / "report.json", report)
        if keep_detections:
            report["_detections"] = all_dets
            report["_store"] = store
            report["_observations"] = result.observations
            report["_T_world_map"] = T_world_map
            report["_objects"] = list(ep.objects)
        return report


def _check_config(config) -> None:
    """Settings this job cannot apply are errors, not silently ignored."""
    from stack.config import ConfigError, StoreConfig

    if config.loop_closure.enabled and config.store.gate_m != StoreConfig().gate_m:
        raise ConfigError("key 'store.gate_m': with loop_closure.enabled the map is placed again with the "
                          f"default gate ({StoreConfig().gate_m} m); leave it at the default")


def _map_png(path, ep, T_world_map, poses, map_points, labels, report) -> None:
    from testbed.plots import plt, save

    fig, ax = plt.subplots(figsize=(9, 6.5))
    if map_points:
        pts = transform_points(T_world_map, np.vstack(map_points))
        pts = pts[(pts[:, 2] > 0.05) & (pts[:, 2] < 2.0)]
        ax.scatter(pts[:, 0], pts[:, 1], s=0.2, c="0.55", label="LiDAR map")
    est = (T_world_map @ poses)[:, :2, 3]
    truth = ep.groundtruth  # the simulator's record (rows: t, x, y, ...), or a bag's poses (replay)
    gt = truth.rows()[:, 1:3] if hasattr(truth, "rows") else np.asarray(truth.T_world_base)[:, :2, 3]
    ax.plot(gt[:, 0], gt[:, 1], "g-", lw=1, label="ground-truth path")
    ax.plot(est[:, 0], est[:, 1], "b--", lw=1, label="LiDAR odometry")
    for row in labels:
        tx, ty = row["truth_xyz"][:2]
        ax.plot(tx, ty, "ko", ms=5)
        ax.annotate(row["object"], (tx, ty), xytext=(5, 5), textcoords="offset points", fontsize=7)
    s = report["labels_summary"]
    colors = {"correct": "tab:blue", "misplaced": "red", "phantom": "magenta"}
    for m in s.get("map_labels", []):
        lx, ly = m["label_xyz"][:2]
        ax.plot(lx, ly, "x", color=colors[m["verdict"]], ms=7, mew=2)
        if m["verdict"] != "correct":
            ax.annotate(f"{m['class']} ({m['verdict']})", (lx, ly), xytext=(5, -9), textcoords="offset points",
                        fontsize=6, color=colors[m["verdict"]])
    for c in report.get("candidates", []):
        ax.plot(c["xyz"][0], c["xyz"][1], ".", color="0.6", ms=4)
    ax.plot([], [], "ko", label="object truth")
    for verdict, color in colors.items():
        ax.plot([], [], "x", color=color, label=f"label: {verdict}" if verdict == "correct" else f"false label: {verdict}")
    ax.plot([], [], ".", color="0.6", label="candidate (not published)")
    prec = "-" if s["map_precision"] is None else f"{100 * s['map_precision']:.0f} %"
    err = s["mean_error_m"]
    ax.set_title(f"{report['scenario']} seed {report['seed']}: {s['labels_in_map']} labels, {s['correct_labels']} correct, "
                 f"{s['false_labels']} false (precision {prec}); {s['correct_labels']}/{s['objects']} objects, "
                 f"mean error {'-' if err is None else f'{100 * err:.1f} cm'}", fontsize=9)
    ax.set_aspect("equal")
    ax.legend(loc="lower left", fontsize=7)
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    save(fig, path)


def print_summary(report: dict) -> None:
    s = report["labels_summary"]
    d = report["detection"]
    o = report["odometry"]
    detector = report.get("detector", DOPE_DETECTOR)
    setup = f"{report['input']}, {report['stages']} stages, FPR {'on' if report['fpr'] else 'off'}" \
        if detector == DOPE_DETECTOR else f"detector {detector}"
    if report.get("profile", "full") != "full":
        setup += f", {report['profile']} profile: camera {report['camera_rate_hz']:g} Hz"
    print(f"{report['scenario']} seed {report['seed']} ({setup}, policy {report['policy']}): "
          f"{report['sim_seconds']:.0f} s simulated in {report['wall_seconds']:.0f} s")
    print(f"{'object':<12} {'id':>3} {'error cm':>9} {'false':>6}")
    for r in report["labels"]:
        err = "-" if r["error_m"] is None else f"{100 * r['error_m']:.1f}"
        print(f"{r['object']:<12} {str(r['id'] or '-'):>3} {err:>9} {str(r['false_label'] if not r['missing'] else 'missing'):>6}")
    for m in s["map_labels"]:
        if m["verdict"] != "correct":
            near = m.get("nearest_object_m")
            where = f"{100 * m['error_m']:.1f} cm from {m['object']}" if m["object"] else \
                f"no {m['class']} there (nearest object {'-' if near is None else f'{100 * near:.0f} cm'})"
            print(f"false label: {m['class']} #{m['id']} ({m['verdict']}, {where}, {m['observations']} observations)")
    print(summary_line(s))
    prec = "-" if d["precision"] is None else f"{100 * d['precision']:.1f}%"
    rec = "-" if d["recall"] is None else f"{100 * d['recall']:.1f}%"
    if d.get("instances", 0) is None:
        rec = "not scored (no segmentation image)"
    fps = "-" if d["fps"] is None else f"{d['fps']:.1f}"
    rpe = o["rpe_trans_pct"]
    rpe = "- (too short a path)" if rpe is None or not math.isfinite(rpe) else f"{rpe:.2f} %"
    print(f"detection: {d['predictions']} predictions in {d['frames']} frames, precision {prec}, recall {rec}, "
          f"{fps} frames/s; odometry ATE {100 * o['ate_rmse_m']:.1f} cm, RPE {rpe}")
    if "loop_closures" in o:
        print(f"loop closure: {o['loop_closures']} closures ({o['false_loop_closures']} false), "
              f"{o['loop_candidates_rejected']} candidates rejected; ATE {100 * o['ate_rmse_m']:.1f} cm closed-loop, "
              f"{100 * o['ate_rmse_odometry_only_m']:.1f} cm odometry only")
