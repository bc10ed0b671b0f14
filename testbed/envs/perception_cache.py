"""Perception of an episode, computed once and kept on disk for the labelling env's fast mode.

What the stack perceives in an episode does not depend on how the labels are chosen: the robot
drives the scenario's route, KISS-ICP gives its pose, DOPE gives detections. So the expensive part
(simulation, odometry, DOPE) runs once per (scenario, seed, light, duration, input, stages,
weights) and the env replays it at thousands of steps per second.

Files, under ``cache_dir()`` (``$DOPESLAM_CACHE/perception``, default ``~/.cache/dopeslam/perception``), named by
a hash of those fields (:class:`PerceptionSpec`):

- ``<stem>.json``        the spec it was built for, the objects' ground truth, camera, timings
- ``<stem>.npz``         per camera frame: stamp, estimated and true base pose; per detection:
                         frame, stage count, class, map-frame pose, belief sum, FPR verdict, range,
                         key points, the camera's position in the map (the viewpoint); the odometry
                         trajectory, ``T_base_cam``, the floor plane the odometry fitted (``floor_plane``:
                         n x, n y, n z, d in map, NaN without one) and a thinned LiDAR map for rendering
- ``<stem>.thumbs.npz``  a small JPEG per frame (the camera image, or the depth image for depth
                         input), read only when rendering

No pickle: plain arrays and JSON. A file whose spec differs from the one asked for (any field,
or the format version) is rebuilt; writes are atomic (temporary file, then ``os.replace``), and
a lock file keeps two processes from building the same episode at once.

:class:`LivePerception` drives the stack's pipeline (:class:`stack.pipeline.DopeSlam`) and hands
over one fused camera frame at a time; the builder drains it, the active-labelling env steps it
while the policy drives.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import math
import os
import tempfile
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from stack.interfaces import detect
from stack.messages import CameraFrame, Detection, LidarScan
from stack.transforms import interpolate_trajectory, inv

log = logging.getLogger(__name__)

CACHE_VERSION = 2  # 2: per-detection camera position, T_base_cam, the odometry's floor plane
FPR_RULE_VERSION = 2  # 1: belief sum + depth check; 2: + colour check, recalibrated fall-back
DEFAULT_THUMB = (160, 120)

DetectorFactory = Callable[[object], object]
"""episode -> detector with ``detect(frame) -> list[Detection]`` (and optionally
``detect_stages(frame) -> {stage count: list[Detection]}``, every stage count from one pass). A
factory whose ``images_only`` attribute is true promises a detector that reads only the frames'
images, never the episode's ground truth: the cache build then renders no segmentation image."""


class PerceptionCacheError(RuntimeError):
    """A cached episode that cannot be used (names the file and what is wrong)."""


def cache_dir(path: str | os.PathLike | None = None) -> Path:
    """The cache folder: ``path``, else ``perception/`` in the cache root (``testbed.settings.cache_dir``)."""
    if path is None:
        from testbed.settings import cache_dir as cache

        return cache("perception", create=False)
    return Path(path).expanduser()


def file_sha256(path: str | os.PathLike, n_hex: int = 16) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:n_hex]


@dataclass(frozen=True)
class PerceptionSpec:
    """Everything the perception of an episode depends on; its hash names the cache files."""

    scenario: str  # scenario name
    scenario_sha: str  # hash of the validated scenario (an edited TOML is a different episode)
    seed: int
    light: float
    duration: float
    input: str  # "rgb" | "depth"
    stages: tuple  # stage counts kept (all of 1..6 when the detector gives them from one pass)
    detector: str  # detector identity: kind and weights hash
    thumb: tuple = DEFAULT_THUMB
    renderer: str = "auto"  # sim.camera renderer: auto (EGL when it loads) | egl | tiny
    version: int = CACHE_VERSION

    def key(self) -> str:
        text = json.dumps(self.to_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:20]

    def stem(self) -> str:
        return f"{self.scenario}-seed{self.seed}-{self.input}-{self.key()}"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["stages"], d["thumb"] = list(self.stages), list(self.thumb)
        return d

    @staticmethod
    def from_dict(d: dict) -> "PerceptionSpec":
        return PerceptionSpec(str(d["scenario"]), str(d["scenario_sha"]), int(d["seed"]), float(d["light"]),
                              float(d["duration"]), str(d["input"]), tuple(int(s) for s in d["stages"]),
                              str(d["detector"]), tuple(int(v) for v in d["thumb"]), str(d.get("renderer", "auto")),
                              int(d["version"]))


def make_spec(scenario, seed: int | None = None, duration: float | None = None, light: float | None = None,
              input_mode: str = "rgb", stages=(6,), detector_id: str = "", thumb=DEFAULT_THUMB,
              renderer: str = "auto") -> PerceptionSpec:
    """The spec of an episode; ``scenario`` is a bundled name, a TOML path or a Scenario."""
    from sim.scenario import Scenario, load_scenario

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    if input_mode not in ("rgb", "depth"):
        raise ValueError(f"input: expected 'rgb' or 'depth', got {input_mode!r}")
    if not detector_id:
        raise ValueError("detector_id: expected a non-empty detector identity (kind and weights hash)")
    stages = tuple(sorted({int(s) for s in (stages if hasattr(stages, "__iter__") else (stages,))}))
    if not stages or min(stages) < 1 or max(stages) > 6:
        raise ValueError(f"stages: expected stage counts in 1..6, got {stages}")
    return PerceptionSpec(
        scenario=sc.name, scenario_sha=hashlib.sha256(sc.model_dump_json().encode()).hexdigest()[:16],
        seed=sc.seed if seed is None else int(seed), light=float(sc.light if light is None else light),
        duration=float(sc.duration if duration is None else duration), input=input_mode, stages=stages,
        detector=detector_id, thumb=(int(thumb[0]), int(thumb[1])), renderer=str(renderer))


# --- The pipeline: sim -> odometry -> DOPE -> fusion, one camera frame at a time ------------------

@dataclass
class FusedFrame:
    """One camera frame after DOPE and fusion: its detections carried into the map frame."""

    index: int
    stamp: float
    T_map_base: np.ndarray | None  # estimated pose at the image's time (None before any scan)
    T_world_base: np.ndarray  # ground truth at the image's time
    detections: dict  # stage count -> dict of arrays (cls, xyz, quat, belief, fpr, range, kp, cam)
    image: np.ndarray | None  # what the detector looked at, for rendering (RGB uint8, or depth colourised)
    detect_seconds: float


DET_FIELDS = {"cls": (np.int16, ()), "xyz": (np.float64, (3,)), "quat": (np.float64, (4,)),
              "belief": (np.float64, ()), "fpr": (np.bool_, ()), "range": (np.float64, ()),
              "kp": (np.float32, (9, 2)), "cam": (np.float64, (3,))}


def _empty_dets() -> dict:
    return {k: np.zeros((0, *shape), dtype=dt) for k, (dt, shape) in DET_FIELDS.items()}


def visual(frame: CameraFrame, input_mode: str) -> np.ndarray | None:
    """The image shown for a frame: RGB for RGB input, the depth image colourised for depth input."""
    if input_mode == "depth" and frame.depth_m is not None:
        d = np.clip(frame.depth_m / 3.0, 0.0, 1.0)
        img = cv2.applyColorMap((255 * (1.0 - d)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
        img[frame.depth_m <= 0] = 0
        return np.ascontiguousarray(img)
    return frame.rgb


class LivePerception:
    """Runs an episode through the stack's pipeline (:class:`stack.pipeline.DopeSlam`) and yields
    :class:`FusedFrame` in time order, each once the pipeline fused it.

    The pipeline's rule for images: a camera frame waits until the odometry has a pose after its
    stamp (the next LiDAR sweep) and is fused with the interpolated pose; the last frames are fused
    with the odometry's short extrapolation when the episode ends; detections without a pose are
    dropped (``dropped_no_pose``). Every kept stage count's detections of a frame are fused with its
    one pose; the labelling env keeps its own map, so the pipeline's object store stays empty.
    """

    def __init__(self, episode, detector, classes: list[str], input_mode: str = "rgb",
                 stages: tuple = (6,), keep_images: bool = True):
        from stack.lidar_slam import LidarOdometry
        from stack.pipeline import DopeSlam

        self.ep = episode
        self.detector = detector
        self.class_index = {c: i for i, c in enumerate(classes)}
        self.input_mode = input_mode
        self.stages = tuple(stages)
        self.keep_images = keep_images
        self.odom = LidarOdometry(episode.T_base_velodyne)
        self.T_base_cam = episode.T_base_camera
        self.T_cam_base = inv(self.T_base_cam)
        self.pipeline = DopeSlam(self.odom, None, self.T_base_cam, {}, on_fused_image=self._on_fused,
                                 map_objects=False)
        self.n_frames = 0
        self.last_camera_frame: CameraFrame | None = None
        self._waiting: dict[int, dict] = {}  # frame index -> what the FusedFrame needs besides the fusion
        self._ready: deque = deque()  # fused frames not yet yielded
        self._map_xy: list[np.ndarray] = []
        self._compactions = 0

    @property
    def dropped_no_pose(self) -> int:
        return self.pipeline.unposed

    @property
    def map_points(self) -> list[np.ndarray]:
        """The LiDAR map so far, (x, y) in ``map`` of the points 0.05-2 m above ``base_link``, float32."""
        if self.pipeline.map_compactions != self._compactions:  # the pipeline thinned its map: start anew
            self._compactions, self._map_xy = self.pipeline.map_compactions, []
        for pts in self.pipeline.map_points[len(self._map_xy):]:
            self._map_xy.append(pts[(pts[:, 2] > 0.05) & (pts[:, 2] < 2.0), :2].astype(np.float32))
        return self._map_xy

    def _detect(self, frame: CameraFrame) -> dict[int, list[Detection]]:
        if len(self.stages) > 1 or hasattr(self.detector, "detect_stages"):
            if not hasattr(self.detector, "detect_stages"):
                raise ValueError(f"stages {self.stages}: this detector gives one stage count per pass "
                                 "(no detect_stages); ask for one stage count")
            by_stage = self.detector.detect_stages(frame)
            missing = [s for s in self.stages if s not in by_stage]
            if missing:
                raise ValueError(f"detector gave stage counts {sorted(by_stage)}, not {missing}")
            return {s: by_stage[s] for s in self.stages}
        return {self.stages[0]: detect(self.detector, frame)}

    def _on_fused(self, fi) -> None:
        """A frame the pipeline fused (``stack.pipeline.FusedImage``) -> a :class:`FusedFrame`."""
        rec = self._waiting.pop(fi.index)
        rows: dict[int, list] = {s: [] for s in self.stages}
        for s, det, obs in zip(rec["stage_of"], fi.detections, fi.observations):
            if obs is None:
                continue
            if det.cls not in self.class_index:
                raise ValueError(f"detector returned class {det.cls!r}; expected one of {sorted(self.class_index)}")
            kp = np.asarray(det.keypoints_px, dtype=np.float32).reshape(9, 2)
            rows[s].append((self.class_index[det.cls], obs.xyz, obs.quat_xyzw, obs.belief_sum, obs.fpr_pass,
                            obs.range_m, kp, obs.cam_xyz))
        out = {}
        for s, stage_rows in rows.items():
            arrs = _empty_dets()
            if stage_rows:
                for k, col in zip(DET_FIELDS, zip(*stage_rows)):
                    arrs[k] = np.asarray(col, dtype=DET_FIELDS[k][0])
            out[s] = arrs
        self._ready.append(FusedFrame(fi.index, fi.stamp, fi.T_map_base, rec["T_world_base"], out, rec["image"],
                                      rec["seconds"]))

    def frames(self, on_scan: Callable[[LidarScan], None] | None = None) -> Iterator[FusedFrame]:
        for msg in self.ep.frames():
            if isinstance(msg, CameraFrame):
                self.last_camera_frame = msg
                t0 = time.perf_counter()
                by_stage = self._detect(msg)
                seconds = time.perf_counter() - t0
                image = visual(msg, self.input_mode) if self.keep_images else None
                self._waiting[self.n_frames] = {
                    "stage_of": [s for s, dets in by_stage.items() for _ in dets], "image": image,
                    "seconds": seconds, "T_world_base": msg.T_world_camera @ self.T_cam_base}
                self.n_frames += 1
                self.pipeline.on_image(msg, [d for dets in by_stage.values() for d in dets])
            else:
                self.pipeline.on_message(msg)
                if on_scan is not None and isinstance(msg, LidarScan):
                    on_scan(msg)
            while self._ready:
                yield self._ready.popleft()
        self.pipeline.finish()
        while self._ready:
            yield self._ready.popleft()


# --- Building and loading the cache -----------------------------------------------------------------

@dataclass
class Perception:
    """A cached episode, in memory."""

    spec: PerceptionSpec
    meta: dict
    arrays: dict
    thumbs_path: Path | None = None
    _thumbs: tuple | None = field(default=None, repr=False)

    @property
    def n_frames(self) -> int:
        return int(len(self.arrays["frame_stamp"]))

    def thumbnail(self, i: int) -> np.ndarray | None:
        """Frame i's small image (RGB uint8), decoded on demand."""
        if self.thumbs_path is None or not self.thumbs_path.exists():
            return None
        if self._thumbs is None:
            with np.load(self.thumbs_path, allow_pickle=False) as z:
                self._thumbs = (z["jpeg"], z["offsets"])
        buf, off = self._thumbs
        if not 0 <= i < len(off) - 1 or off[i + 1] == off[i]:
            return None
        bgr = cv2.imdecode(buf[off[i]:off[i + 1]], cv2.IMREAD_COLOR)
        return None if bgr is None else bgr[..., ::-1]


@contextmanager
def _atomic(path: Path):
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp makes it 0600
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextmanager
def _lock(path: Path):
    with open(path, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def paths_for(spec: PerceptionSpec, folder: Path) -> tuple[Path, Path, Path]:
    stem = folder / spec.stem()
    return stem.with_suffix(".json"), stem.with_suffix(".npz"), Path(str(stem) + ".thumbs.npz")


def load(spec: PerceptionSpec, folder=None) -> Perception | None:
    """The cached perception for ``spec``, or None when there is none or it was built for another spec."""
    folder = cache_dir(folder)
    meta_path, npz_path, thumbs_path = paths_for(spec, folder)
    if not meta_path.exists() or not npz_path.exists():
        return None
    try:
        meta = json.loads(meta_path.read_text())
        stored = PerceptionSpec.from_dict(meta["spec"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        log.warning("%s: unreadable cache metadata (%s); rebuilding", meta_path, e)
        return None
    if stored != spec:
        log.info("%s: built for another spec (%s); rebuilding", meta_path,
                 ", ".join(k for k, v in spec.to_dict().items() if stored.to_dict().get(k) != v))
        return None
    try:
        with np.load(npz_path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        log.warning("%s: unreadable cache arrays (%s); rebuilding", npz_path, e)
        return None
    return Perception(spec, meta, arrays, thumbs_path)


def build(spec: PerceptionSpec, detector_factory: DetectorFactory, folder=None, scenario=None,
          progress: bool = True) -> Perception:
    """Run the episode through the stack and write its perception to the cache. ``progress``: a bar
    with an ETA (where :mod:`testbed.progress` shows bars) and a log line every 15 s."""
    from sim.episode import Episode
    from sim.objects import load_catalog
    from sim.scenario import load_scenario
    from testbed.progress import SecondsBar

    folder = cache_dir(folder)
    folder.mkdir(parents=True, exist_ok=True)
    classes = list(load_catalog())
    sc = load_scenario(spec.scenario if scenario is None else scenario) if not hasattr(scenario, "route") else scenario
    wall0 = time.perf_counter()
    frame_stamp, frame_T_est, frame_T_true, frame_secs = [], [], [], []
    det_cols: dict[str, list] = {k: [] for k in DET_FIELDS}
    det_frame, det_stage = [], []
    jpeg, offsets = [], [0]
    # the segmentation image is ground truth that only a detector reading the truth needs; the camera is
    # rendered in a second process while this one runs the detector (the same frames, in the same order)
    segmentation = not getattr(detector_factory, "images_only", False)
    with Episode(sc, seed=spec.seed, duration=spec.duration, light=spec.light, renderer=spec.renderer,
                 segmentation=segmentation, render_worker=True) as ep:
        if ep.sc.name != spec.scenario:
            raise ValueError(f"scenario {ep.sc.name!r} does not match the spec's {spec.scenario!r}")
        live = LivePerception(ep, detector_factory(ep), classes, spec.input, spec.stages)
        n_expected = int(round(spec.duration * ep.sc.sensors.camera_rate)) + 1
        last_log = time.perf_counter()
        bar = SecondsBar(spec.duration, f"caching {spec.scenario} seed {spec.seed}") if progress else None
        for ff in live.frames():
            if bar is not None:
                bar.update_to(ff.stamp, frames=ff.index + 1)
            frame_stamp.append(ff.stamp)
            frame_T_est.append(np.full((4, 4), np.nan) if ff.T_map_base is None else ff.T_map_base)
            frame_T_true.append(ff.T_world_base)
            frame_secs.append(ff.detect_seconds)
            for s, arrs in ff.detections.items():
                n = len(arrs["cls"])
                det_frame.extend([ff.index] * n)
                det_stage.extend([s] * n)
                for k in DET_FIELDS:
                    det_cols[k].append(arrs[k])
            data = b""
            if ff.image is not None:
                small = cv2.resize(ff.image, spec.thumb, interpolation=cv2.INTER_AREA)
                ok, enc = cv2.imencode(".jpg", small[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 80])
                data = enc.tobytes() if ok else b""
            jpeg.append(data)
            offsets.append(offsets[-1] + len(data))
            if progress and time.perf_counter() - last_log > 15:
                last_log = time.perf_counter()
                log.info("caching %s seed %d: frame %d of ~%d (%.0f s)", spec.scenario, spec.seed, ff.index + 1,
                         n_expected, last_log - wall0)
        if bar is not None:
            bar.close()
        traj_stamp, traj_T = live.odom.trajectory()
        if len(traj_stamp) == 0:
            raise PerceptionCacheError(f"{spec.scenario} seed {spec.seed}: the odometry registered no scan")
        T_world_map = ep.T_world_base_at(traj_stamp[0])
        objects = [{"name": o.name, "cls": o.cls, "T_world_obj": np.asarray(o.T_world_obj).tolist(),
                    "dims": np.asarray(o.dims).tolist()} for o in ep.objects]
        info = ep.camera_info
        stage_seconds = None
        if len(spec.stages) > 1 and live.last_camera_frame is not None:
            stage_seconds = measure_stage_seconds(live.detector, live.last_camera_frame, spec.stages)
        sim_seconds = float(getattr(ep, "sim_seconds", spec.duration))
    T_est = np.asarray(frame_T_est).reshape(-1, 4, 4)
    missing = np.isnan(T_est[:, 0, 0])
    if missing.any():  # frames before the first scan: the first pose, as the map is defined there
        T_est[missing] = interpolate_trajectory(traj_stamp, traj_T, np.asarray(frame_stamp)[missing])
    arrays = {
        "frame_stamp": np.asarray(frame_stamp, dtype=np.float64),
        "frame_T_map_base": T_est,
        "frame_T_world_base": np.asarray(frame_T_true).reshape(-1, 4, 4),
        "frame_detect_s": np.asarray(frame_secs, dtype=np.float64),
        "det_frame": np.asarray(det_frame, dtype=np.int32),
        "det_stage": np.asarray(det_stage, dtype=np.int8),
        **{f"det_{k}": (np.concatenate(v) if v else _empty_dets()[k]).astype(DET_FIELDS[k][0])
           for k, v in det_cols.items()},
        "traj_stamp": traj_stamp, "traj_T_map_base": traj_T,
        "map_xy": np.concatenate(live.map_points) if live.map_points else np.zeros((0, 2), np.float32),
        "T_world_map": T_world_map,
        "T_base_cam": np.asarray(live.T_base_cam, dtype=np.float64),
        "floor_plane": floor_array(live.odom.floor_plane_map()),
    }
    meta = {
        "format": "dopeslam-perception", "spec": spec.to_dict(), "key": spec.key(), "classes": classes,
        "objects": objects, "camera": {"width": info.width, "height": info.height, "K": info.K.tolist()},
        "frames": len(frame_stamp), "detections": int(len(det_frame)),
        "dropped_no_pose": live.dropped_no_pose, "detect_seconds_per_frame": float(np.mean(frame_secs)) if frame_secs else None,
        "stage_seconds": stage_seconds, "build_seconds": time.perf_counter() - wall0, "sim_seconds": sim_seconds,
        "camera_rate_hz": float(sc.sensors.camera_rate),
    }
    meta_path, npz_path, thumbs_path = paths_for(spec, folder)
    with _atomic(thumbs_path) as tmp, open(tmp, "wb") as f:
        np.savez(f, jpeg=np.frombuffer(b"".join(jpeg), dtype=np.uint8), offsets=np.asarray(offsets, dtype=np.int64))
    with _atomic(npz_path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    with _atomic(meta_path) as tmp:  # written last: its presence says the arrays are complete
        tmp.write_text(json.dumps(meta, indent=1))
    log.info("cached %s seed %d (%d frames, %d detections) in %.0f s: %s", spec.scenario, spec.seed,
             meta["frames"], meta["detections"], meta["build_seconds"], npz_path)
    return Perception(spec, meta, arrays, thumbs_path)


def load_or_build(spec: PerceptionSpec, detector_factory: DetectorFactory | None, folder=None,
                  progress: bool = True, scenario=None) -> Perception:
    """The cached perception, building it first when it is missing or stale. ``scenario``: the name,
    path or Scenario the spec was made from (needed to build when it is not a bundled one)."""
    folder = cache_dir(folder)
    got = load(spec, folder)
    if got is not None:
        return got
    if detector_factory is None:
        raise PerceptionCacheError(f"{cache_dir(folder) / spec.stem()}.npz: not cached and no detector to build it")
    folder.mkdir(parents=True, exist_ok=True)
    with _lock(folder / f".{spec.stem()}.lock"):
        got = load(spec, folder)  # another process may have built it while we waited
        if got is not None:
            return got
        return build(spec, detector_factory, folder, scenario, progress=progress)


# --- Detectors and their identities ------------------------------------------------------------------

def dope_detector_id(input_mode: str, weights=None, detector=None) -> str:
    """Identity of the real DOPE detector: input, hashes of its weights, FPR thresholds and colour-model
    files, the version of the FPR rule (the FPR verdicts are part of the cached perception), and the
    network's precision when it is not fp32 (fp32 caches keep the identity they had before the setting), with
    int8's calibration file's hash."""
    path = Path(getattr(detector, "weights_path", None) or dope_weights_path(input_mode, weights))
    if not path.exists():
        raise PerceptionCacheError(f"{path}: no DOPE weights for input {input_mode!r} (train them with "
                                   "`dopeslam dope train`, or pass weights=...)")
    thresholds = path.parent / f"fpr_thresholds_{input_mode}.json"
    fpr = file_sha256(thresholds, 12) if thresholds.exists() else "none"
    ident = f"dope:{input_mode}:w{file_sha256(path)}:fpr{fpr}:rule{FPR_RULE_VERSION}"
    if input_mode == "depth":  # which depth windows run (floor-only windows are skipped) is part of the perception
        from stack.dope_fpr import WINDOW_MIN_PIXELS

        ident += f":windows{getattr(detector, 'window_min_pixels', WINDOW_MIN_PIXELS)}:fitted-range"
    if input_mode == "rgb":
        from stack.dope_fpr import default_colour_model_path

        colour = default_colour_model_path()
        ident += f":colour{file_sha256(colour, 12) if colour.exists() else 'none'}"
    from stack.dope_fpr import effective_precision

    precision = getattr(detector, "precision", None) or effective_precision()
    if precision != "fp32":
        ident += f":{precision}"
    if precision == "int8":  # the maps follow the activation scales too
        from stack.dope.int8 import calibration_path

        cal = Path(getattr(detector, "int8_calibration", None) or calibration_path(path))
        ident += file_sha256(cal, 12) if cal.exists() else "none"
    return ident


def dope_weights_path(input_mode: str, weights=None) -> Path:
    from stack import dope_fpr

    return Path(weights) if weights is not None else dope_fpr.default_weights(input_mode)


def dope_stage_counts(input_mode: str, stages: int, weights=None) -> tuple:
    """The stage counts a cache of the real DOPE keeps: all of 1..(the network's stages) when the
    detector gives them from one pass (``detect_stages``), else the requested one."""
    from stack.dope.net import WeightsError, read_weights
    from stack.dope_fpr import DopeDetector

    path = dope_weights_path(input_mode, weights)
    if not path.exists():
        raise PerceptionCacheError(f"{path}: no DOPE weights for input {input_mode!r} (train them with "
                                   "`dopeslam dope train`, or pass weights=...)")
    config = read_weights(path)["config"]
    try:
        n = int(config["stages"])
    except (KeyError, TypeError, ValueError):
        raise WeightsError(f"{path}: its 'config' gives no number of stages") from None
    if hasattr(DopeDetector, "detect_stages"):
        return tuple(range(1, n + 1))
    return (min(int(stages), n),)


def dope_factory(input_mode: str, stages: int, weights=None) -> tuple[DetectorFactory, str, tuple]:
    """(factory, detector id, stage counts it gives) for the real DOPE detector with FPR verdicts."""
    from testbed.run import make_detector

    kept = dope_stage_counts(input_mode, stages, weights)
    det = make_detector(input_mode, max(kept), True, weights)

    def factory(ep):
        return det

    factory.images_only = True  # DOPE reads the images alone
    return factory, dope_detector_id(input_mode, weights, det), kept


def measure_stage_seconds(detector, frame: CameraFrame, stages: tuple, repeats: int = 3) -> dict[str, float]:
    """DOPE time per frame at each stage count (the fastest of a few runs on one frame), for the
    precision-against-compute trade-off (the paper's Figure 6)."""
    out = {}
    for s in stages:
        best = math.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            detector.detect_stages(frame, [s])
            best = min(best, time.perf_counter() - t0)
        out[str(s)] = best
    return out


def floor_array(floor) -> np.ndarray:
    """(n x, n y, n z, d) of a floor plane (n, d) in map (n.x + d = height above it); NaN for None."""
    if floor is None:
        return np.full(4, np.nan)
    n, d = floor
    return np.array([*np.asarray(n, dtype=float).reshape(3), float(d)])


def floor_of(perception: "Perception") -> tuple[np.ndarray, float] | None:
    """The floor plane (n, d) in map a cached episode's odometry fitted, or None."""
    a = perception.arrays.get("floor_plane")
    if a is None or not np.all(np.isfinite(a)):
        return None
    return np.asarray(a[:3], dtype=float), float(a[3])


def finite(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None
