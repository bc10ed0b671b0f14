"""Camera streams of a scenario rendered once and cached on disk, so that the many seeded re-runs of
the monocular stack (RANSAC seeds, detector variants) do not pay for rendering again.

A stream holds, per camera frame: the stamp, the RGB image, the ground-truth camera pose and, per
object, its tight visible box (from the segmentation), visible fraction and distance. Plus the
episode's facts: intrinsics, extrinsics, objects, the ground-truth base trajectory.

Cache: ``$DOPESLAM_CACHE/topomap_streams`` (default ``~/.cache/dopeslam/topomap_streams``), one ``.npz``
(arrays only, no pickle) + one ``.json`` per (scenario, seed, light, size, duration).
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stack.messages import CameraInfo, ObjectTruth
from stack.transforms import inv, transform_points
from testbed.io import atomic_path, write_text

log = logging.getLogger(__name__)
STREAM_VERSION = 2
DEFAULT_SIZE = (640, 480)


def cache_root() -> Path:
    from testbed.settings import cache_dir

    return cache_dir("topomap_streams")


@dataclass
class CameraStream:
    scenario: str
    seed: int
    light: float
    info: CameraInfo
    stamps: np.ndarray  # (N,)
    rgb: np.ndarray  # (N, H, W, 3) uint8
    T_world_camera: np.ndarray  # (N, 4, 4)
    T_base_camera: np.ndarray  # (4, 4)
    objects: list[ObjectTruth]
    boxes: np.ndarray  # (N, M, 4) x0 y0 x1 y1 visible box per object (NaN where not visible), pixels
    visible: np.ndarray  # (N, M) visible pixels / projected hull area
    distance: np.ndarray  # (N, M) camera-to-centroid distance, m
    gt_stamps: np.ndarray  # base trajectory
    T_world_base: np.ndarray
    render_seconds: float = 0.0
    T_odom_base: np.ndarray | None = None  # (N, 4, 4) wheel odometry at each image (the robot's, drifting)

    def __len__(self) -> int:
        return len(self.stamps)

    def gray(self, i: int) -> np.ndarray:
        import cv2

        return cv2.cvtColor(self.rgb[i], cv2.COLOR_RGB2GRAY)

    def moving_range(self, min_speed: float = 0.02) -> tuple[int, int]:
        """First and last frame index while the robot moves (ground truth: for choosing evaluation spans)."""
        p = self.T_world_camera[:, :3, 3]
        v = np.r_[0.0, np.linalg.norm(np.diff(p, axis=0), axis=1)] / np.maximum(np.r_[1.0, np.diff(self.stamps)], 1e-9)
        idx = np.flatnonzero(v > min_speed)
        if len(idx) == 0:
            return 0, len(self) - 1
        return int(max(0, idx[0] - 1)), int(idx[-1])

    def object_in_view(self, i: int, k: int, min_visible: float = 0.3) -> bool:
        return bool(np.isfinite(self.boxes[i, k, 0]) and self.visible[i, k] >= min_visible)


def _key(scenario: str, seed: int, light: float, size, duration) -> str:
    s = f"v{STREAM_VERSION}/{scenario}/{seed}/{light:.3f}/{size[0]}x{size[1]}/{duration}"
    return hashlib.sha1(s.encode()).hexdigest()[:12]


def _atomic_savez(path: Path, **arrays) -> None:
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, **arrays)


def _atomic_text(path: Path, text: str) -> None:
    write_text(path, text)


def render_stream(scenario=None, seed: int | None = None, light: float | None = None, size=DEFAULT_SIZE,
                  duration: float | None = None) -> CameraStream:
    """Run the scenario's episode with the camera only (no LiDAR) at ``size`` and collect the stream."""
    from sim.episode import Episode
    from sim.scenario import load_scenario

    sc = load_scenario(scenario)
    sc.sensors.camera_width, sc.sensors.camera_height = int(size[0]), int(size[1])
    sc.sensors.lidar = False
    t0 = time.perf_counter()
    stamps, rgbs, poses, boxes, vis, dist = [], [], [], [], [], []
    with Episode(sc, seed=seed, duration=duration, light=light) as ep:
        bodies = [ep.world.object_bodies[o.name] for o in ep.objects]
        last = t0
        from stack.messages import CameraFrame, WheelOdometry

        odom = np.eye(4)
        odoms = []
        for msg in ep.frames():
            if isinstance(msg, WheelOdometry):
                odom = msg.T_odom_base
            if not isinstance(msg, CameraFrame):
                continue
            odoms.append(odom.copy())
            seg = msg.extra["segmentation"] & ((1 << 24) - 1)
            truth = ep.image_truth(msg)
            b = np.full((len(bodies), 4), np.nan)
            for k, body in enumerate(bodies):
                ys, xs = np.nonzero(seg == body)
                if len(xs) >= 4:
                    b[k] = [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]
            stamps.append(msg.stamp)
            rgbs.append(msg.rgb)
            poses.append(msg.T_world_camera)
            boxes.append(b)
            vis.append([t["visible_fraction"] for t in truth])
            dist.append([t["distance_m"] if t["in_front"] else np.inf for t in truth])
            if time.perf_counter() - last > 10:
                last = time.perf_counter()
                log.info("rendering %s seed %s: t = %.1f / %.1f s", sc.name, ep.seed, msg.stamp, ep.duration)
        stream = CameraStream(sc.name, ep.seed, ep.light, ep.camera_info, np.asarray(stamps), np.asarray(rgbs),
                              np.asarray(poses), ep.T_base_camera, list(ep.objects), np.asarray(boxes),
                              np.asarray(vis, dtype=float), np.asarray(dist, dtype=float),
                              ep.groundtruth.stamps[::8].copy(), ep.groundtruth.T_world_base[::8].copy(),
                              time.perf_counter() - t0, np.asarray(odoms))
    return stream


def save_stream(stream: CameraStream, path: Path) -> None:
    meta = {"version": STREAM_VERSION, "scenario": stream.scenario, "seed": stream.seed, "light": stream.light,
            "width": stream.info.width, "height": stream.info.height, "K": stream.info.K.tolist(),
            "objects": [{"name": o.name, "cls": o.cls, "T_world_obj": o.T_world_obj.tolist(), "dims": list(map(float, o.dims))}
                        for o in stream.objects], "render_seconds": stream.render_seconds}
    _atomic_savez(path.with_suffix(".npz"), stamps=stream.stamps, rgb=stream.rgb, T_world_camera=stream.T_world_camera,
                  T_base_camera=stream.T_base_camera, boxes=stream.boxes, visible=stream.visible,
                  distance=stream.distance, gt_stamps=stream.gt_stamps, T_world_base=stream.T_world_base)
    _atomic_text(path.with_suffix(".json"), json.dumps(meta, indent=1))
    if stream.T_odom_base is not None:
        _atomic_savez(Path(str(path) + ".odom.npz"), stamps=stream.stamps, T_odom_base=stream.T_odom_base)


def load_stream_file(path: Path) -> CameraStream:
    path = Path(path)
    try:
        meta = json.loads(path.with_suffix(".json").read_text())
        a = np.load(path.with_suffix(".npz"))
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable camera stream ({exc})") from exc
    if meta.get("version") != STREAM_VERSION:
        raise ValueError(f"{path}: field 'version': expected {STREAM_VERSION}, got {meta.get('version')}")
    info = CameraInfo(meta["width"], meta["height"], np.array(meta["K"]))
    objs = [ObjectTruth(o["name"], o["cls"], np.array(o["T_world_obj"]), np.array(o["dims"])) for o in meta["objects"]]
    odom = None
    odom_path = Path(str(path.with_suffix("")) + ".odom.npz")
    if odom_path.exists():
        odom = np.load(odom_path)["T_odom_base"]
    return CameraStream(meta["scenario"], meta["seed"], meta["light"], info, a["stamps"], a["rgb"], a["T_world_camera"],
                        a["T_base_camera"], objs, a["boxes"], a["visible"], a["distance"], a["gt_stamps"],
                        a["T_world_base"], meta.get("render_seconds", 0.0), odom)


def wheel_odometry_at(scenario, seed: int, stamps: np.ndarray, light: float | None = None,
                      duration: float | None = None) -> np.ndarray:
    """The episode's wheel odometry at the given image stamps, from a run without sensors (the physics
    and the odometry noise do not depend on rendering, so this equals what the rendered run had)."""
    from sim.episode import Episode
    from sim.scenario import load_scenario
    from stack.messages import WheelOdometry

    sc = load_scenario(scenario)
    sc.sensors.lidar = False
    sc.sensors.camera = False
    out = np.tile(np.eye(4), (len(stamps), 1, 1))
    odom = np.eye(4)
    k = 0
    with Episode(sc, seed=seed, duration=duration, light=light) as ep:
        for msg in ep.frames():
            if isinstance(msg, WheelOdometry):
                odom = msg.T_odom_base
                while k < len(stamps) and stamps[k] <= msg.stamp + 1e-9:
                    out[k] = odom
                    k += 1
    out[k:] = odom
    return out


def camera_stream(scenario=None, seed: int | None = None, light: float | None = None, size=None,
                  duration: float | None = None, cache: bool = True) -> CameraStream:
    """The scenario's camera stream, from the cache when it is there (rendered and cached otherwise).
    ``size``: (width, height), default the scenario's camera."""
    from sim.scenario import load_scenario

    sc = load_scenario(scenario)
    size = tuple(size) if size is not None else (sc.sensors.camera_width, sc.sensors.camera_height)
    seed = sc.seed if seed is None else int(seed)
    light = sc.light if light is None else float(light)
    path = cache_root() / f"{sc.name}_s{seed}_{_key(sc.model_dump_json(), seed, light, size, duration)}"
    if cache and path.with_suffix(".npz").exists() and path.with_suffix(".json").exists():
        try:
            stream = load_stream_file(path)
        except ValueError as exc:
            log.warning("re-rendering: %s", exc)
        else:
            if stream.T_odom_base is None:  # a cache from before odometry was kept: add it
                stream.T_odom_base = wheel_odometry_at(scenario, seed, stream.stamps, light, duration)
                _atomic_savez(Path(str(path) + ".odom.npz"), stamps=stream.stamps, T_odom_base=stream.T_odom_base)
            return stream
    log.info("rendering the camera stream of %s (seed %d, light %.2f, %dx%d)", sc.name, seed, light, *size)
    stream = render_stream(scenario, seed, light, size, duration)
    if cache:
        save_stream(stream, path)
    return stream


def project_object(stream: CameraStream, i: int, k: int) -> np.ndarray | None:
    """Pixel of object k's centroid in frame i (None when behind the camera)."""
    p = transform_points(inv(stream.T_world_camera[i]), stream.objects[k].T_world_obj[:3, 3][None])[0]
    if p[2] <= 0.05:
        return None
    K = stream.info.K
    return np.array([K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]])
