"""A scripted drive-through: the Jackal follows the scenario's route through the physics, and the
sensors produce timestamped frames in time order, each with its ground truth.

One seed drives everything random here: physics is deterministic, and the sensor-noise and
wheel-odometry streams are children of ``np.random.SeedSequence(seed)``.
"""
from __future__ import annotations

import logging
import math
import os
import tempfile
from collections import deque
from typing import Iterator

import cv2
import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from sim.camera import RenderWorker, default_camera_info, new_client, render_rgbd
from sim.events import WorldEvents
from sim.lidar import BeamPattern, BoxRayCaster, PacketLayout
from sim.objects import cuboid_keypoints
from sim.robot import Jackal
from sim.scenario import Scenario, ScenarioError, load_scenario, with_overrides
from sim.world import build_world
from stack.messages import CameraFrame, LidarScan, WheelOdometry
from stack.transforms import from_xyz_quat, interpolate_trajectory, inv, transform_points, yaw_of

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
        x, y = float(T_world_base[0, 3]), float(T_world_base[1, 3])
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
        w = min(max(3.0 * err, -1.5), 1.5)
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
    """``base_link`` in ``world`` at every physics step so far: per step its stamp, position and
    quaternion (64 bytes; the 4x4 matrices are rebuilt as they are read, bit for bit the ones the
    episode computed from the same quaternion).

    The newest ``memory_rows`` steps (a little over two minutes at 240 Hz) stay in memory; older
    ones are appended to an unnamed temporary file, deleted when the record is garbage-collected or
    the process ends (``close()`` deletes it at once). So an episode of any length keeps the same
    memory; a long one costs 64 bytes of disk per step (55 MB an hour at 240 Hz). Lookups
    (:meth:`T_world_base_at`) read only the rows they interpolate between. Stamps must increase.
    """

    ROW = 8  # stamp, x, y, z, qx, qy, qz, qw (float64)
    BLOCK = 1024  # rows per entry of the stamp index (the first stamp of every block is kept in memory)

    def __init__(self, memory_rows: int = 1 << 15):
        if memory_rows < 1 or memory_rows % self.BLOCK:
            raise ValueError(f"memory_rows must be a positive multiple of {self.BLOCK}, got {memory_rows}")
        self._buf = np.empty((memory_rows, self.ROW))  # pages are touched only as rows arrive
        self._n_buf = 0  # rows in the buffer
        self._n_file = 0  # rows in the file (all older than the buffer's)
        self._file = None
        self._firsts: list[float] = []  # first stamp of each block of BLOCK rows

    def __len__(self) -> int:
        return self._n_file + self._n_buf

    def add(self, stamp: float, xyz, quat_xyzw) -> None:
        """One step: ``base_link``'s position and orientation (x, y, z, w) in ``world`` at ``stamp``."""
        if self._n_buf == len(self._buf):
            self._spill()
        n = len(self)
        if n % self.BLOCK == 0:
            self._firsts.append(float(stamp))
        row = self._buf[self._n_buf]
        row[0] = stamp
        row[1:4] = xyz
        row[4:8] = quat_xyzw
        self._n_buf += 1

    def _spill(self) -> None:
        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="dopeslam-groundtruth-")
        self._file.seek(0, os.SEEK_END)
        self._file.write(self._buf[:self._n_buf].tobytes())
        self._file.flush()
        self._n_file += self._n_buf
        self._n_buf = 0

    def close(self) -> None:
        """Delete the temporary file now (the record then holds only its in-memory rows)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def rows(self, i0: int = 0, i1: int | None = None) -> np.ndarray:
        """Rows ``[i0, i1)`` as a new (k, 8) array: stamp, x, y, z, qx, qy, qz, qw."""
        n = len(self)
        i1 = n if i1 is None else min(int(i1), n)
        i0 = max(0, int(i0))
        out = np.empty((max(0, i1 - i0), self.ROW))
        if i1 <= i0:
            return out
        f1 = min(i1, self._n_file)
        if i0 < f1:
            if self._file is None:
                raise RuntimeError("the ground-truth record's older rows were deleted (close() was called)")
            want = (f1 - i0) * self.ROW * 8
            data = bytearray()
            while len(data) < want:
                chunk = os.pread(self._file.fileno(), want - len(data), i0 * self.ROW * 8 + len(data))
                if not chunk:
                    raise RuntimeError("the ground-truth record's temporary file is shorter than expected")
                data += chunk
            out[:f1 - i0] = np.frombuffer(bytes(data), dtype=np.float64).reshape(-1, self.ROW)
        if i1 > self._n_file:
            b0 = max(i0, self._n_file)
            out[b0 - i0:] = self._buf[b0 - self._n_file:i1 - self._n_file]
        return out

    @staticmethod
    def _matrices(rows: np.ndarray) -> np.ndarray:
        out = np.zeros((len(rows), 4, 4))
        if len(rows):
            out[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
        out[:, :3, 3] = rows[:, 1:4]
        out[:, 3, 3] = 1.0
        return out

    def window(self, i0: int = 0, i1: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(stamps, T_world_base (k, 4, 4)) of rows ``[i0, i1)``."""
        r = self.rows(i0, i1)
        return r[:, 0].copy(), self._matrices(r)

    @property
    def base_stamps(self) -> np.ndarray:
        """Every stamp so far (a new array)."""
        return self.rows()[:, 0].copy()

    @property
    def base_poses(self) -> np.ndarray:
        """Every pose so far as (N, 4, 4) (a new array: 136 bytes a step while it is held)."""
        return self._matrices(self.rows())

    T_world_base = base_poses
    stamps = base_stamps

    def _count_below(self, t: np.ndarray) -> np.ndarray:
        """Per query, how many stamps are below it (``np.searchsorted(stamps, t, "left")``), reading
        one block of stamps per block the queries fall in."""
        firsts = np.asarray(self._firsts)
        blocks = np.searchsorted(firsts, t, side="left") - 1  # the last block starting below t
        out = np.zeros(len(t), dtype=np.int64)
        for b in np.unique(blocks[blocks >= 0]):
            sel = blocks == b
            stamps = self.rows(b * self.BLOCK, (b + 1) * self.BLOCK)[:, 0]
            out[sel] = b * self.BLOCK + np.searchsorted(stamps, t[sel], side="left")
        return out

    def T_world_base_at(self, t) -> np.ndarray:
        """``interpolate_trajectory(stamps, T_world_base, t)`` over the whole record, bit for bit, reading
        only the two rows around each query: (4, 4) for a scalar t, else (M, 4, 4)."""
        n = len(self)
        if n == 0:
            raise ValueError("no ground truth yet")
        tq = np.atleast_1d(np.asarray(t, dtype=float))
        if n <= 2:
            r = self.rows()
            return interpolate_trajectory(r[:, 0], self._matrices(r), t)
        # the segment the whole trajectory's interpolation takes for each query (see interpolate_trajectory)
        ends = self.rows(0, 1)[0, 0], self.rows(n - 1, n)[0, 0]
        j = np.clip(self._count_below(np.clip(tq, *ends)) - 1, 0, n - 2)
        need = np.unique(np.concatenate([j, j + 1]))
        runs = np.split(need, np.flatnonzero(np.diff(need) > 1) + 1)  # consecutive rows read together
        r = np.concatenate([self.rows(run[0], run[-1] + 1) for run in runs])
        return interpolate_trajectory(r[:, 0], self._matrices(r), t)


class Episode:
    """A scenario running in its own PyBullet client. Iterate ``frames()`` once."""

    def __init__(self, scenario: Scenario | str | None = None, seed: int | None = None,
                 duration: float | None = None, light: float | None = None, renderer: str = "auto",
                 camera: bool | None = None, lidar: bool | None = None, render_worker: bool | None = None,
                 camera_rate: float | None = None, segmentation: bool = True, lidar_packets: bool | None = None):
        """``render_worker``: render the camera in a second process (``sim.camera.RenderWorker``) so the
        rendering overlaps the physics, the LiDAR and whatever consumes the frames; the frames and
        their order are the same either way. An integer N: N such processes, each drawing every N-th
        frame (N frames in flight). None: as the environment variable DOPESLAM_RENDER_WORKER says (1 =
        on), else off. ``camera_rate``: the camera's rate in Hz in place of the scenario's
        ``[sensors] camera_rate``. ``segmentation=False``: frames carry no segmentation image (cheaper
        to render; ``image_truth`` then gives no visible fraction and ``occluder_fraction`` is 0).
        ``lidar_packets``: the Velodyne publishes VLP-32C data packets (``stack.velodyne``) and each
        sweep is their decoding, in place of the scenario's ``[sensors] lidar_packets``."""
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
        self.lidar_packets = bool(s.lidar_packets if lidar_packets is None else lidar_packets)
        self.camera_info = default_camera_info(s.camera_width, s.camera_height)
        if render_worker is None:
            render_worker = os.environ.get("DOPESLAM_RENDER_WORKER", "0") == "1"
        self._render_workers: list[RenderWorker] = []
        if self.sc.events:  # the worker's world would not follow the events
            render_worker = False
        if self.use_camera and render_worker:  # started first: they build their worlds while this one does
            self._render_workers = [RenderWorker(self.sc, self.camera_info, renderer, segmentation=self.segmentation)
                                    for _ in range(max(1, int(render_worker)))]
        self.render_processes = len(self._render_workers)  # the camera's, as started
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
        self.packet_layout = PacketLayout(self.beams) if self.lidar_packets else None
        self.follower = RouteFollower(self.sc)
        self.groundtruth = GroundTruth()
        self.T_world_map: np.ndarray | None = None
        self.wall_seconds = 0.0
        # who decides which camera frames are drawn (set before iterating frames()): an object with
        # ``see(msg)``, shown every message as it is made, and ``wants(t)``, asked when a frame is due;
        # a frame not wanted is not rendered and comes out without pixels (``extra["unrendered"]``).
        # None: every frame is drawn
        self.camera_demand = None
        self.unrendered_frames = 0
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

    def T_world_base_at(self, t: float | np.ndarray) -> np.ndarray:
        """``base_link`` in ``world`` at t (interpolated between physics steps; clamped at the ends)."""
        return self.groundtruth.T_world_base_at(t)

    def close(self) -> None:
        for worker in getattr(self, "_render_workers", []):
            worker.close()
        self._render_workers = []
        if self.client is not None:
            p.disconnect(self.client)
            self.client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- the loop ---------------------------------------------------------------------------------
    def frames(self) -> Iterator[LidarScan | CameraFrame | WheelOdometry]:
        """The sensors' messages in time order. While a message is out, ``groundtruth_rows`` is the
        number of ground-truth rows there were when it was made (with N render workers a frame
        comes out N camera periods later, after more physics steps; a recorder that writes the
        ground truth up to each message writes the same bag either way)."""
        import time

        s = self.sc.sensors
        steps = int(round(self.duration / self.dt))
        cam_every = max(1, int(round(1.0 / (self.camera_rate * self.dt))))
        odo_every = max(1, int(round(1.0 / (s.wheel_odometry_rate * self.dt))))
        sweep_steps = max(1, int(round(self.beams.period / self.dt)))
        pattern = self.packet_layout or self.beams
        dirs = pattern.directions()
        col_t = pattern.column_times()
        az = pattern.azimuths()
        workers = self._render_workers
        # frames the render workers are drawing, oldest first: [worker, t, T_world_cam, ground-truth rows,
        # the (message, rows) made after it, held back to keep the time order]
        flight: deque = deque()
        submitted = 0
        demand = self.camera_demand
        wall0 = time.perf_counter()
        for k in range(steps + 1):
            t = k * self.dt
            xyz, quat = self.robot.xyz_quat_world_base()
            T_world_base = from_xyz_quat(xyz, quat)
            if self.events is not None and self.events.step(t, T_world_base[:2, 3]):
                self._boxes_changed = True
            self.groundtruth.add(t, xyz, quat)
            if k > 0:
                self.robot.update_odometry(self.dt)
            rows = len(self.groundtruth)
            out = []
            if k % odo_every == 0:
                out.append(WheelOdometry(t, self.robot.T_odom_base.copy(), self.robot.odo_v, self.robot.odo_w))
            if self.use_lidar and k >= sweep_steps and k % sweep_steps == 0:
                scan = self._lidar_scan(t - self.beams.period, dirs, col_t, az)
                if self.T_world_map is None:
                    self.T_world_map = self.T_world_base_at(scan.stamp)
                out.append(scan)
            if demand is not None:
                for m in out:
                    demand.see(m)
            if self.use_camera and k % cam_every == 0:
                if demand is not None and not demand.wants(t):
                    out.append(self._unrendered_frame(t, T_world_base))
                elif not workers:
                    out.append(self._camera_frame(t, T_world_base))
                else:  # hand out the oldest frame once every worker is busy, then start this one
                    if flight:
                        flight[-1][4].extend((m, rows) for m in out)
                    else:
                        yield from self._marked((m, rows) for m in out)
                    out = []
                    # the oldest frame is collected before this one starts and handed out after, so its
                    # consumer works while the worker draws
                    landed = self._landed(flight.popleft()) if len(flight) == len(workers) else []
                    worker = workers[submitted % len(workers)]
                    submitted += 1
                    flight.append([worker, *self._submit_frame(t, T_world_base, worker), rows, []])
                    yield from self._marked(landed)
            if flight:
                flight[-1][4].extend((m, rows) for m in out)
            else:
                yield from self._marked((m, rows) for m in out)
            if k == steps:
                break
            v, w = self.follower(t, T_world_base)
            self.robot.command(v, w, self.dt)
            p.stepSimulation(physicsClientId=self.client)
        while flight:
            yield from self._marked(self._landed(flight.popleft()))
        self.groundtruth_rows = len(self.groundtruth)
        self.wall_seconds = time.perf_counter() - wall0
        self.sim_seconds = steps * self.dt

    def _landed(self, entry) -> list:
        """A drawn frame (collected from its worker now), then the messages made after it, with their
        ground-truth rows."""
        worker, t, T_world_cam, rows, after = entry
        return [(self._collect_frame(t, T_world_cam, worker), rows)] + after

    def _marked(self, pairs):
        for msg, rows in pairs:
            self.groundtruth_rows = rows
            yield msg

    def _lidar_scan(self, stamp: float, dirs, col_t, az) -> LidarScan:
        gt = self.groundtruth
        if getattr(self, "_boxes_changed", False):  # objects moved or people walked: cast the world as it is now
            self.caster = BoxRayCaster(self.world.boxes)
            self._boxes_changed = False
        n = int(round(self.beams.period / self.dt)) + 2
        T_wb = _interpolate_poses(*gt.window(len(gt) - n), stamp + col_t)
        T_ws = T_wb @ self._T_base_velodyne  # (A, 4, 4) sensor pose at each column's firing time
        R = T_ws[:, :3, :3]
        # world ray directions per component: R @ dirs, with dirs (A, R, 3) split once per episode
        if getattr(self, "_dirs_split", None) is None or self._dirs_split[0].shape != dirs.shape[:2]:
            self._dirs_split = tuple(np.ascontiguousarray(dirs[..., k]) for k in range(3))
        sx, sy, sz = self._dirs_split
        dw = [R[:, i, 0, None] * sx + R[:, i, 1, None] * sy + R[:, i, 2, None] * sz for i in range(3)]
        o = [np.ascontiguousarray(T_ws[:, i, 3, None]) for i in range(3)]
        az_world = az + np.arctan2(R[:, 1, 0], R[:, 0, 0])
        layout = self.packet_layout
        spread = 0.0 if layout is None else layout.model.max_azimuth_offset_rad()
        ranges, hit = self.caster.cast_components(*o, *dw, az_world, self.beams.range_max, azimuth_spread=spread)
        if self.sc.sensors.noise:
            ranges = ranges + self.rng_lidar.standard_normal(ranges.shape) * self.beams.range_noise
        ok = np.isfinite(ranges) & (ranges >= self.beams.range_min) & (ranges <= self.beams.range_max)
        if layout is not None:
            return self._packet_scan(stamp, ranges, hit, ok, T_ws[0].copy())
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

    def _packet_scan(self, stamp: float, ranges, hit, ok, T_world_sensor: np.ndarray) -> LidarScan:
        """The sweep as a VLP-32C publishes it: ranges in the sensor's distance steps, reflectivity
        0-255, packed into its data packets; the scan is their decoding (what replay of a bag of
        them gives, bit for bit) and carries them."""
        from stack.velodyne import BLOCKS, build_packets, decode_blocks

        layout = self.packet_layout
        model = layout.model
        counts = np.zeros(ranges.shape, dtype=np.int64)
        counts[ok] = np.rint(ranges[ok] / model.distance_resolution)
        refl = np.zeros(ranges.shape, dtype=np.int64)
        refl[ok] = np.clip(np.rint(100.0 * self.caster.refl[hit[ok]]), 0, 255)
        ring_of_laser = model.ring_of_laser
        n_blocks = layout.packets * BLOCKS
        by_block = [np.zeros((n_blocks, counts.shape[1]), dtype=np.int64) for _ in range(2)]
        by_block[0][: layout.columns] = counts[:, ring_of_laser]  # laser-ID order
        by_block[1][: layout.columns] = refl[:, ring_of_laser]
        stamp_ns = int(round(stamp * 1e9))
        shape = (layout.packets, BLOCKS, counts.shape[1])
        counts, refl = by_block[0].reshape(shape), by_block[1].reshape(shape)
        packets = build_packets(layout.azimuth_centideg, counts, refl, stamp_ns + layout.offsets_ns)
        scan = decode_blocks(layout.azimuth_centideg, counts, refl, packets.stamps_ns, stamp_ns, model)  # = decode_sweep(packets)
        scan.T_world_sensor = T_world_sensor
        scan.packets = packets
        self.lidar_points += int(len(scan.points))
        if self.events is not None and self.events.walkers:
            self.lidar_person_points += int(np.isin(hit[ok], list(self.events.person_boxes)).sum())
        return scan

    def _camera_frame(self, t: float, T_world_base: np.ndarray) -> CameraFrame:
        T_world_cam = T_world_base @ self._T_base_camera
        rng = np.random.default_rng(self._frame_seed())
        rgb, depth, seg = render_rgbd(self.client, T_world_cam, self.camera_info, self.light_at(t), rng,
                                      self.sc.sensors.noise, self.renderer, segmentation=self.segmentation)
        return CameraFrame(t, self.camera_info, rgb, depth, T_world_cam, {"segmentation": seg})

    def _unrendered_frame(self, t: float, T_world_base: np.ndarray) -> CameraFrame:
        """A frame nobody will look at: its time and pose, no pixels. Its noise seed is drawn all the
        same, so every later frame is the one it would have been."""
        self._frame_seed()
        self.unrendered_frames += 1
        return CameraFrame(t, self.camera_info, None, None, T_world_base @ self._T_base_camera,
                           {"segmentation": None, "unrendered": True})

    def _frame_seed(self) -> int:
        """Each frame's noise has its own seed, drawn in frame order, so a frame is the same whichever
        process renders it."""
        return int(self.rng_camera.integers(2**63))

    def _submit_frame(self, t: float, T_world_base: np.ndarray, worker: RenderWorker) -> tuple[float, np.ndarray]:
        T_world_cam = T_world_base @ self._T_base_camera
        worker.submit(T_world_cam, T_world_base, self.light_at(t), self.sc.sensors.noise, self._frame_seed())
        return t, T_world_cam

    def _collect_frame(self, t: float, T_world_cam: np.ndarray, worker: RenderWorker) -> CameraFrame:
        rgb, depth, seg = worker.collect()
        return CameraFrame(t, self.camera_info, rgb, depth, T_world_cam, {"segmentation": seg})

    # --- per-image ground truth ---------------------------------------------------------------------
    def image_truth(self, frame: CameraFrame) -> list[dict]:
        """Per object: projected key points (DOPE order), whether in front, and the visible fraction."""
        info = frame.info
        seg = frame.extra.get("segmentation")
        ids = None  # the segmentation's body ids (low 24 bits), computed once for every object's count
        T_cam_world = inv(frame.T_world_camera)
        out = []
        for obj in self.world.objects:
            T_cam_obj = T_cam_world @ obj.T_world_obj
            kp = transform_points(T_cam_obj, cuboid_keypoints(obj.dims))
            in_front = bool(np.all(kp[:, 2] > 0.05))
            uv = np.full((9, 2), np.nan)
            visible = 0.0 if seg is not None else None  # None: not rendered (Episode(segmentation=False))
            if in_front:
                uv = np.column_stack([info.fx * kp[:, 0] / kp[:, 2] + info.cx, info.fy * kp[:, 1] / kp[:, 2] + info.cy])
                hull = cv2.convexHull(uv[:8].astype(np.float32))
                area = float(cv2.contourArea(hull))
                if seg is not None and area > 1:
                    if ids is None:
                        ids = seg & ((1 << 24) - 1)
                    px = int(np.count_nonzero(ids == self.world.object_bodies[obj.name]))
                    visible = float(min(1.0, px / area))
            out.append({"name": obj.name, "cls": obj.cls, "T_cam_obj": T_cam_obj, "keypoints_px": uv,
                        "in_front": in_front, "visible_fraction": visible, "distance_m": float(np.linalg.norm(T_cam_obj[:3, 3]))})
        return out
