"""A scripted drive-through: the Jackal follows the scenario's route through the physics, and the
sensors produce timestamped frames in time order, each with its ground truth.

One seed drives everything random here: physics is deterministic, and the sensor-noise and
wheel-odometry streams are children of ``np.random.SeedSequence(seed)``.
"""
from __future__ import annotations

import logging
import math
import os
from typing import Iterator

import cv2
import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from sim.camera import RenderWorker, default_camera_info, new_client, render_rgbd
from sim.events import WorldEvents
from sim.lidar import BeamPattern, BoxRayCaster
from sim.objects import cuboid_keypoints
from sim.robot import Jackal
from sim.scenario import Scenario, ScenarioError, load_scenario, with_overrides
from sim.world import build_world
from stack.messages import CameraFrame, LidarScan, WheelOdometry
from stack.transforms import interpolate_trajectory, inv, transform_points, yaw_of

log = logging.getLogger(__name__)


class RouteFollower:
    """Drives to each waypoint in turn (heading control, slowing for turns), with the route's pauses."""

    def __init__(self, sc: Scenario):
        self.route = sc.route
        self.idx = 0
        self.pause_until = sc.route.start_pause
        self.pauses = {int(i): s for i, s in sc.route.pauses}
        self.done = False
        self.closest = np.full(len(self.route.waypoints), np.inf)  # how near the robot came to each waypoint

    def __call__(self, t: float, T_world_base: np.ndarray) -> tuple[float, float]:
        x, y = T_world_base[0, 3], T_world_base[1, 3]
        for i, w in enumerate(self.route.waypoints):
            self.closest[i] = min(self.closest[i], math.hypot(w[0] - x, w[1] - y))
        if self.done or t < self.pause_until:
            return 0.0, 0.0
        wp = self.route.waypoints[self.idx]
        d = math.hypot(wp[0] - x, wp[1] - y)
        if d < self.route.tolerance:
            self.pause_until = t + self.pauses.get(self.idx, 0.0)
            self.idx += 1
            if self.idx == len(self.route.waypoints):
                self.done = True
            if self.done:
                return 0.0, 0.0
            return self(t, T_world_base)
        speed = wp[2] if len(wp) == 3 else self.route.speed
        err = (math.atan2(wp[1] - y, wp[0] - x) - yaw_of(T_world_base) + math.pi) % (2 * math.pi) - math.pi
        w = float(np.clip(3.0 * err, -1.5, 1.5))
        v = speed * max(0.0, math.cos(err)) ** 4
        if d < 0.4 and abs(err) > 0.4:
            v = 0.0
        if self.idx == len(self.route.waypoints) - 1 or self.pauses.get(self.idx, 0) > 0:
            v = min(v, 0.6 * d + 0.03)  # arrive gently where the robot stops
        return v, w


def _interpolate_poses(stamps: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(M, 4, 4) poses at times ``t`` (clamped to the ends): linear translation, rotation along the
    geodesic between neighbouring samples (what ``interpolate_trajectory`` gives, for many query
    times at the cost of one small rotation log per segment)."""
    if len(stamps) == 1:
        return np.repeat(poses[:1], len(t), axis=0)
    t = np.clip(t, stamps[0], stamps[-1])
    i = np.clip(np.searchsorted(stamps, t, side="right") - 1, 0, len(stamps) - 2)
    f = (t - stamps[i]) / (stamps[i + 1] - stamps[i])
    R = poses[:, :3, :3]
    seg_rotvec = Rotation.from_matrix(np.einsum("nji,njk->nik", R[:-1], R[1:])).as_rotvec()  # R_i^T R_i+1
    out = np.zeros((len(t), 4, 4))
    out[:, :3, :3] = R[i] @ Rotation.from_rotvec(f[:, None] * seg_rotvec[i]).as_matrix()
    out[:, :3, 3] = poses[i, :3, 3] + f[:, None] * (poses[i + 1, :3, 3] - poses[i, :3, 3])
    out[:, 3, 3] = 1.0
    return out


class GroundTruth:
    """``base_link`` in ``world`` at every physics step so far, kept in two arrays that grow by doubling
    (a pose costs its 136 bytes, not a Python object per step: a long episode's record stays compact,
    and reading it is a view, not a copy)."""

    def __init__(self, capacity: int = 4096):
        self._stamps = np.empty(capacity)
        self._poses = np.empty((capacity, 4, 4))
        self._n = 0

    def add(self, stamp: float, T_world_base: np.ndarray) -> None:
        if self._n == len(self._stamps):  # twice the room; the new half's pages stay untouched until used
            stamps, poses = np.empty(2 * self._n), np.empty((2 * self._n, 4, 4))
            stamps[:self._n], poses[:self._n] = self._stamps, self._poses
            self._stamps, self._poses = stamps, poses
        self._stamps[self._n] = stamp
        self._poses[self._n] = T_world_base
        self._n += 1

    @property
    def base_stamps(self) -> np.ndarray:
        return self._stamps[:self._n]

    @property
    def base_poses(self) -> np.ndarray:
        return self._poses[:self._n]

    T_world_base = base_poses
    stamps = base_stamps


class Episode:
    """A scenario running in its own PyBullet client. Iterate ``frames()`` once."""

    def __init__(self, scenario: Scenario | str | None = None, seed: int | None = None,
                 duration: float | None = None, light: float | None = None, renderer: str = "auto",
                 camera: bool | None = None, lidar: bool | None = None, render_worker: bool | None = None,
                 camera_rate: float | None = None, segmentation: bool = True):
        """``render_worker``: render the camera in a second process (``sim.camera.RenderWorker``) so the
        rendering overlaps the physics, the LiDAR and whatever consumes the frames; the frames and
        their order are the same either way. None: as the environment variable DOPESLAM_RENDER_WORKER
        says (1 = on), else off. ``camera_rate``: the camera's rate in Hz in place of the scenario's
        ``[sensors] camera_rate``. ``segmentation=False``: frames carry no segmentation image (cheaper
        to render; ``image_truth`` then gives no visible fraction and ``occluder_fraction`` is 0)."""
        self.sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        with_overrides(self.sc, seed=seed, duration=duration, light=light)  # checked as the file is: ScenarioError
        if camera_rate is not None and not 0.0 < float(camera_rate) <= 60.0:
            raise ScenarioError(f"camera rate {camera_rate!r}: expected a rate in (0, 60] Hz")
        self.camera_rate = float(self.sc.sensors.camera_rate if camera_rate is None else camera_rate)
        self.segmentation = bool(segmentation)
        self.seed = self.sc.seed if seed is None else int(seed)
        self.duration = self.sc.duration if duration is None else float(duration)
        self.light = self.sc.light if light is None else float(light)
        self._light_schedule = [] if light is not None else list(self.sc.light_schedule)  # an override wins
        s = self.sc.sensors
        self.use_camera = s.camera if camera is None else camera
        self.use_lidar = s.lidar if lidar is None else lidar
        self.camera_info = default_camera_info(s.camera_width, s.camera_height)
        if render_worker is None:
            render_worker = os.environ.get("DOPESLAM_RENDER_WORKER", "0") == "1"
        self._render_worker = None
        if self.sc.events:  # the worker's world would not follow the events
            render_worker = False
        if self.use_camera and render_worker:  # started first: it builds its world while this one does
            self._render_worker = RenderWorker(self.sc, self.camera_info, renderer, segmentation=self.segmentation)
        ss = np.random.SeedSequence(self.seed)
        self.rng_lidar, self.rng_camera, self.rng_odom = (np.random.default_rng(c) for c in ss.spawn(3))
        self.client, self.renderer = new_client(renderer if self.use_camera else "tiny")  # no EGL without a camera
        p.setGravity(0, 0, -9.81, physicsClientId=self.client)
        self.dt = 1.0 / self.sc.physics_hz
        p.setTimeStep(self.dt, physicsClientId=self.client)
        self.world = build_world(self.client, self.sc)
        self.events = WorldEvents(self.world, self.sc.events) if self.sc.events else None
        self.lidar_points = 0  # points in the sweeps so far ...
        self.lidar_person_points = 0  # ... of them on people walking through
        x, y, yaw_deg = self.sc.robot.start
        self.robot = Jackal(self.client, (x, y, math.radians(yaw_deg)), self.rng_odom)
        self.caster = BoxRayCaster(self.world.boxes)
        self.beams = BeamPattern.from_hardware(s.lidar_azimuth_steps, s.lidar_rate)
        self.follower = RouteFollower(self.sc)
        self.groundtruth = GroundTruth()
        self.T_world_map: np.ndarray | None = None
        self.wall_seconds = 0.0
        # settle the robot on its wheels before time starts
        for _ in range(int(0.5 / self.dt)):
            p.stepSimulation(physicsClientId=self.client)
        self._T_base_velodyne = self.robot.T_base_velodyne
        self._T_base_camera = self.robot.T_base_camera

    # --- public facts ---------------------------------------------------------------------------
    @property
    def T_base_velodyne(self) -> np.ndarray:
        return self._T_base_velodyne.copy()

    @property
    def T_base_camera(self) -> np.ndarray:
        return self._T_base_camera.copy()

    @property
    def objects(self):
        """The objects as they are now (after the last event so far; at the end: the final world)."""
        return self.world.objects

    def objects_at(self, t: float):
        """The objects as they were at time ``t`` (events applied up to then)."""
        return self.events.truth_at(t) if self.events else list(self.world.objects)

    @property
    def event_log(self) -> list[dict]:
        """What happened to the world: moves, removals, additions, walks started (time order)."""
        return list(self.events.log) if self.events else []

    def past_positions(self):
        """(name, class, centroid in world) of each place an object stood and no longer stands."""
        return self.events.past_positions() if self.events else []

    def occluder_fraction(self, frame: CameraFrame) -> float:
        """The fraction of the image covered by people walking through (from the segmentation)."""
        seg = frame.extra.get("segmentation")
        if seg is None or not self.events or not self.events.walkers:
            return 0.0
        ids = np.array(sorted(self.events.person_bodies))
        return float(np.isin(seg & ((1 << 24) - 1), ids).mean())

    def light_at(self, t: float) -> float:
        """The light level at time t: the scenario's ``light_schedule`` if any, else ``light``."""
        level = self.light
        for t_from, lvl in self._light_schedule:
            if t >= t_from:
                level = float(lvl)
        return level

    def T_world_base_at(self, t: float) -> np.ndarray:
        return interpolate_trajectory(self.groundtruth.stamps, self.groundtruth.T_world_base, t)

    def close(self) -> None:
        if getattr(self, "_render_worker", None) is not None:
            self._render_worker.close()
            self._render_worker = None
        if self.client is not None:
            p.disconnect(self.client)
            self.client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- the loop ---------------------------------------------------------------------------------
    def frames(self) -> Iterator[LidarScan | CameraFrame | WheelOdometry]:
        import time

        s = self.sc.sensors
        steps = int(round(self.duration / self.dt))
        cam_every = max(1, int(round(1.0 / (self.camera_rate * self.dt))))
        odo_every = max(1, int(round(1.0 / (s.wheel_odometry_rate * self.dt))))
        sweep_steps = max(1, int(round(self.beams.period / self.dt)))
        dirs = self.beams.directions()
        col_t = self.beams.column_times()
        az = self.beams.azimuths()
        worker = self._render_worker
        in_flight = None  # (t, T_world_cam) of the frame the render worker is drawing
        held = []  # messages after that frame, held back to keep the time order
        wall0 = time.perf_counter()
        for k in range(steps + 1):
            t = k * self.dt
            T_world_base = self.robot.T_world_base()
            if self.events is not None and self.events.step(t, T_world_base[:2, 3]):
                self._boxes_changed = True
            self.groundtruth.add(t, T_world_base)
            if k > 0:
                self.robot.update_odometry(self.dt)
            out = []
            if k % odo_every == 0:
                out.append(WheelOdometry(t, self.robot.T_odom_base.copy(), self.robot.odo_v, self.robot.odo_w))
            if self.use_lidar and k >= sweep_steps and k % sweep_steps == 0:
                scan = self._lidar_scan(t - self.beams.period, dirs, col_t, az)
                if self.T_world_map is None:
                    self.T_world_map = self.T_world_base_at(scan.stamp)
                out.append(scan)
            if self.use_camera and k % cam_every == 0:
                if worker is None:
                    out.append(self._camera_frame(t, T_world_base))
                else:  # collect the previous frame, start this one, then hand out what came before it
                    ready = ([self._collect_frame(*in_flight)] if in_flight else []) + held + out
                    held, out = [], []
                    in_flight = self._submit_frame(t, T_world_base)
                    yield from ready
            if in_flight:
                held.extend(out)
            else:
                yield from out
            if k == steps:
                break
            v, w = self.follower(t, T_world_base)
            self.robot.command(v, w, self.dt)
            p.stepSimulation(physicsClientId=self.client)
        if in_flight:
            yield self._collect_frame(*in_flight)
            yield from held
        self.wall_seconds = time.perf_counter() - wall0
        self.sim_seconds = steps * self.dt

    def _lidar_scan(self, stamp: float, dirs, col_t, az) -> LidarScan:
        gt = self.groundtruth
        if getattr(self, "_boxes_changed", False):  # objects moved or people walked: cast the world as it is now
            self.caster = BoxRayCaster(self.world.boxes)
            self._boxes_changed = False
        n = int(round(self.beams.period / self.dt)) + 2
        T_wb = _interpolate_poses(np.asarray(gt.base_stamps[-n:]), np.asarray(gt.base_poses[-n:]), stamp + col_t)
        T_ws = T_wb @ self._T_base_velodyne  # (A, 4, 4) sensor pose at each column's firing time
        R = T_ws[:, :3, :3]
        # world ray directions per component: R @ dirs, with dirs (A, R, 3) split once per episode
        if getattr(self, "_dirs_split", None) is None or self._dirs_split[0].shape != dirs.shape[:2]:
            self._dirs_split = tuple(np.ascontiguousarray(dirs[..., k]) for k in range(3))
        sx, sy, sz = self._dirs_split
        dw = [R[:, i, 0, None] * sx + R[:, i, 1, None] * sy + R[:, i, 2, None] * sz for i in range(3)]
        o = [np.ascontiguousarray(T_ws[:, i, 3, None]) for i in range(3)]
        az_world = az + np.arctan2(R[:, 1, 0], R[:, 0, 0])
        ranges, hit = self.caster.cast_components(*o, *dw, az_world, self.beams.range_max)
        if self.sc.sensors.noise:
            ranges = ranges + self.rng_lidar.standard_normal(ranges.shape) * self.beams.range_noise
        ok = np.isfinite(ranges) & (ranges >= self.beams.range_min) & (ranges <= self.beams.range_max)
        A, Rr = ranges.shape
        r_ok = ranges[ok]
        points = np.column_stack([sx[ok] * r_ok, sy[ok] * r_ok, sz[ok] * r_ok])
        ring = np.broadcast_to(np.arange(Rr, dtype=np.uint16)[None, :], (A, Rr))[ok]
        times = np.broadcast_to(col_t[:, None], (A, Rr))[ok]
        intensity = (100.0 * self.caster.refl[hit[ok]]).astype(np.float32)  # reflectivity of the surface hit
        self.lidar_points += int(r_ok.size)
        if self.events is not None and self.events.walkers:
            self.lidar_person_points += int(np.isin(hit[ok], list(self.events.person_boxes)).sum())
        return LidarScan(stamp, points.astype(np.float32), times.astype(np.float64), ring.copy(), intensity,
                         "velodyne", T_ws[0].copy())

    def _camera_frame(self, t: float, T_world_base: np.ndarray) -> CameraFrame:
        T_world_cam = T_world_base @ self._T_base_camera
        rng = np.random.default_rng(self._frame_seed())
        rgb, depth, seg = render_rgbd(self.client, T_world_cam, self.camera_info, self.light_at(t), rng,
                                      self.sc.sensors.noise, self.renderer, segmentation=self.segmentation)
        return CameraFrame(t, self.camera_info, rgb, depth, T_world_cam, {"segmentation": seg})

    def _frame_seed(self) -> int:
        """Each frame's noise has its own seed, drawn in frame order, so a frame is the same whichever
        process renders it."""
        return int(self.rng_camera.integers(2**63))

    def _submit_frame(self, t: float, T_world_base: np.ndarray) -> tuple[float, np.ndarray]:
        T_world_cam = T_world_base @ self._T_base_camera
        self._render_worker.submit(T_world_cam, T_world_base, self.light_at(t), self.sc.sensors.noise,
                                   self._frame_seed())
        return t, T_world_cam

    def _collect_frame(self, t: float, T_world_cam: np.ndarray) -> CameraFrame:
        rgb, depth, seg = self._render_worker.collect()
        return CameraFrame(t, self.camera_info, rgb, depth, T_world_cam, {"segmentation": seg})

    # --- per-image ground truth ---------------------------------------------------------------------
    def image_truth(self, frame: CameraFrame) -> list[dict]:
        """Per object: projected key points (DOPE order), whether in front, and the visible fraction."""
        info = frame.info
        seg = frame.extra.get("segmentation")
        out = []
        for obj in self.world.objects:
            T_cam_obj = inv(frame.T_world_camera) @ obj.T_world_obj
            kp = transform_points(T_cam_obj, cuboid_keypoints(obj.dims))
            in_front = bool(np.all(kp[:, 2] > 0.05))
            uv = np.full((9, 2), np.nan)
            visible = 0.0 if seg is not None else None  # None: not rendered (Episode(segmentation=False))
            if in_front:
                uv = np.column_stack([info.fx * kp[:, 0] / kp[:, 2] + info.cx, info.fy * kp[:, 1] / kp[:, 2] + info.cy])
                hull = cv2.convexHull(uv[:8].astype(np.float32))
                area = float(cv2.contourArea(hull))
                if seg is not None and area > 1:
                    px = int(np.count_nonzero((seg & ((1 << 24) - 1)) == self.world.object_bodies[obj.name]))
                    visible = float(min(1.0, px / area))
            out.append({"name": obj.name, "cls": obj.cls, "T_cam_obj": T_cam_obj, "keypoints_px": uv,
                        "in_front": in_front, "visible_fraction": visible, "distance_m": float(np.linalg.norm(T_cam_obj[:3, 3]))})
        return out
