"""LiDAR odometry: KISS-ICP (its C++ core) on timestamped Velodyne sweeps, giving ``T_map_base``.

``map`` is the robot's ``base_link`` at the first usable scan (DESIGN.md). KISS-ICP runs in the
sensor frame; the ``base_link -> velodyne`` extrinsic conjugates its poses into base poses:
``T_map_base = T_base_velodyne @ T_velodyne0_velodyne @ inv(T_base_velodyne)``.

The per-scan steps are KISS-ICP's (``KissICP.register_frame``): deskew + range crop, voxelize,
adaptive threshold, predict, align to the local map, update. We call the steps one by one instead of
``register_frame`` because that function assumes every scan follows the previous one by exactly one
sweep; here the prediction and the deskew use a velocity (twist per second) and the real time
between scans, so a dropped scan or a stamp gap gets the right constant-velocity prediction.

Timing: as KISS-ICP does, the per-point times of a sweep are normalised to [0, 1] with their min and
max, and the motion over the sweep is the predicted one over ``max(times_s) - min(times_s)``. Each
point is moved into the sensor frame at the *middle* of the sweep and the pose stamped there
(``scan.stamp`` + the mean of the first and last point times). Why: with the end as reference (where
KISS-ICP deskews to), a velocity error shifts the whole deskewed sweep one way, ICP follows, the next
velocity (from that pose) is off the other way, and the poses ring from scan to scan (measured: +-1 cm
at 0.25 m/s). About the middle, a velocity error only stretches the sweep symmetrically and the loop
is broken. The deskew itself is :func:`deskew_to_middle`, vectorised over the sweep: KISS-ICP's own
(one SE(3) exponential per point, a point at a time) gives the same points to within 1e-10 m and took
four times as long, a fifth of each registration (docs/speed.md). The range crop is KISS-ICP's, about
the sensor at the sweep's end.

Floor: on a flat floor (``floor_constraint``, the default) the floor points are left out of ICP and
height, roll and pitch come from the floor plane instead; see ``_find_floor`` for why.

Defined behaviour on bad input (each logs a warning; none raises):

* non-finite points or times: those points are dropped;
* fewer than ``min_points`` points left after cropping: the scan is skipped (``process`` returns None);
* a stamp not after the previous pose's stamp (time went backwards or repeated): skipped;
* a gap longer than ``gap_factor`` sweeps (dropped scans): constant-velocity prediction over the gap;
* a gap longer than ``max_gap_s`` (a time jump): constant velocity for ``max_gap_s`` only, as the
  robot may have stopped; ICP has to find the rest;
* an ICP correction larger than ``max_correction_m`` from the prediction: kept, but warned about.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from stack.messages import LidarScan, WheelOdometry
from stack.pose_track import PoseTrack
from stack.transforms import interpolate_trajectory, inv

log = logging.getLogger(__name__)


class LidarOdometryConfig(BaseModel):
    """Tuned for an indoor Jackal with a 32-beam Velodyne (rooms up to ~30 m)."""

    model_config = ConfigDict(extra="forbid")

    max_range_m: float = Field(30.0, gt=0, description="points farther than this are dropped")
    min_range_m: float = Field(0.5, ge=0, description="points nearer than this (the robot itself) are dropped")
    deskew: bool = Field(True, description="motion-compensate each sweep with its per-point times")
    voxel_size_m: float = Field(0.2, gt=0, description="local-map voxel; the scan is sampled at 0.5x and 1.5x")
    max_points_per_voxel: int = Field(20, ge=1)
    floor_constraint: bool = Field(True, description="flat floor: height, roll, pitch from the floor plane")
    ground_band_m: float = Field(0.08, gt=0, description="points this near the predicted floor plane are floor")
    min_ground_points: int = Field(200, ge=3, description="fewer floor points: no floor correction this scan")
    max_floor_correction_deg: float = Field(3.0, gt=0, description="larger floor tilt corrections are refused")
    initial_threshold_m: float = Field(0.5, gt=0, description="ICP correspondence scale before motion is seen")
    min_motion_m: float = Field(0.02, ge=0, description="model deviations below this do not adapt the threshold")
    max_iterations: int = Field(500, ge=1)
    convergence: float = Field(1e-4, gt=0, description="ICP stops when a step moves the pose by less than this "
                               "(the norm of its 6 numbers, m and rad); looser is faster and may cost ATE "
                               "(docs/speed.md, 'When ICP stops')")
    threads: int = Field(1, ge=0, description="registration threads; 1 (default) gives the same bytes for a seed "
                         "(more threads reorder float sums: ~1e-16 differences); 0: all cores. KISS-ICP fixes it "
                         "per process, at the first")
    min_points: int = Field(500, ge=10, description="fewer points after cropping: skip the scan")
    gap_factor: float = Field(1.5, gt=1, description="a gap over this many sweeps counts as dropped scans")
    max_gap_s: float = Field(2.0, gt=0, description="constant velocity is extrapolated over at most this")
    max_correction_m: float = Field(0.5, gt=0, description="warn when ICP moves the prediction further")
    max_extrapolation_s: float = Field(0.2, ge=0, description="pose_at may extrapolate this far past the ends")

    def to_kiss(self):
        from kiss_icp.config.config import AdaptiveThresholdConfig, DataConfig, MappingConfig, RegistrationConfig
        from kiss_icp.config.parser import KISSConfig

        return KISSConfig(
            data=DataConfig(max_range=self.max_range_m, min_range=self.min_range_m, deskew=self.deskew),
            mapping=MappingConfig(voxel_size=self.voxel_size_m, max_points_per_voxel=self.max_points_per_voxel),
            registration=RegistrationConfig(max_num_iterations=self.max_iterations,
                                            convergence_criterion=self.convergence,
                                            max_num_threads=self.threads),
            adaptive_threshold=AdaptiveThresholdConfig(initial_threshold=self.initial_threshold_m,
                                                       min_motion_th=self.min_motion_m),
        )


# ---------------------------------------------------------------------------------------------
# SE(3) exponential and logarithm, as 6-vectors (v, omega): used for constant-velocity motion


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w)
    W = _hat(w)
    if th < 1e-9:
        return np.eye(3) + 0.5 * W
    return (np.eye(3) + (1 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * W @ W)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 transform of the twist ``xi = (v, omega)``."""
    xi = np.asarray(xi, dtype=float)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(xi[3:]).as_matrix()
    T[:3, 3] = _left_jacobian(xi[3:]) @ xi[:3]
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist ``(v, omega)`` with ``se3_exp(xi) == T``."""
    w = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    return np.concatenate([np.linalg.solve(_left_jacobian(w), T[:3, 3]), w])


# ---------------------------------------------------------------------------------------------


@dataclass
class OdometryStats:
    scans_in: int = 0
    scans_used: int = 0
    skipped_few_points: int = 0
    skipped_time: int = 0
    nonfinite_points: int = 0
    gaps: int = 0
    time_jumps: int = 0
    large_corrections: int = 0
    seconds: float = 0.0  # wall time spent in process()

    @property
    def hz(self) -> float:
        return self.scans_in / self.seconds if self.seconds > 0 else float("nan")


_CHUNK = 4096  # points per step of the vectorised loops below: their temporaries stay in the cache and
# the allocator's free list (one pass over the whole sweep allocates and page-faults 1.4 MB per temporary)


def deskew_to_middle(points: np.ndarray, times: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Each point of a sweep in the sensor frame at the sweep's middle: ``exp((s - 1/2) xi) @ p`` with
    ``s`` the point's time normalised to [0, 1] by the sweep's first and last, and ``xi = (v, omega)``
    the sensor's motion over the whole sweep (a twist, as :func:`se3_exp` takes it). The same as
    KISS-ICP's deskew (to the sweep's end, ``exp((s - 1) xi)``) followed by ``exp(xi / 2)``, in closed
    form for all points at once (Rodrigues' formula and SE(3)'s left Jacobian; a series where the
    rotation is small). ``points`` (N, 3) float64, ``times`` (N,) with a positive spread."""
    t0, t1 = times.min(), times.max()
    v, w = np.asarray(xi[:3], dtype=float), np.asarray(xi[3:], dtype=float)
    th = float(np.linalg.norm(w))
    # exp(tau xi) p = p + A W p + B (W^2 p + W v) + tau v + C W^2 v, W = hat(omega), a = tau |omega|:
    # A = sin(a) / th, B = (1 - cos a) / th^2, C = (a - sin a) / th^3
    W = _hat(w)
    Wt = np.ascontiguousarray(W.T)  # (n, 3) @ a contiguous (3, 3) takes numpy's fast path
    Wv = W @ v
    M = np.stack([Wv, v, W @ Wv])
    out = np.empty_like(points)
    for i in range(0, len(points), _CHUNK):
        tau = (times[i:i + _CHUNK] - t0) / (t1 - t0) - 0.5
        p, o = points[i:i + _CHUNK], out[i:i + _CHUNK]
        if th < 1e-3:  # |a| < 5e-4: Taylor series, exact to double precision (W = 0 at th = 0)
            a2 = (tau * th) ** 2
            A = tau * (1.0 - a2 / 6.0 * (1.0 - a2 / 20.0))
            B = tau * tau * (0.5 - a2 / 24.0 * (1.0 - a2 / 30.0))
            C = tau * tau * tau * (1.0 / 6.0 - a2 / 120.0 * (1.0 - a2 / 42.0))
        else:
            a = tau * th
            sin_a = np.sin(a)
            A = sin_a / th
            B = 2.0 * np.sin(0.5 * a) ** 2 / th ** 2
            C = (a - sin_a) / th ** 3
        np.matmul(np.stack([B, tau, C], axis=1), M, out=o)  # B W v + tau v + C W^2 v
        o += p
        Wp = p @ Wt
        W2p = Wp @ Wt
        Wp *= A[:, None]
        o += Wp
        W2p *= B[:, None]
        o += W2p
    return out


def _in_range(points: np.ndarray, centre: np.ndarray, near: float, far: float) -> np.ndarray:
    """Whether each point lies strictly between ``near`` and ``far`` metres from ``centre``."""
    d = points - centre
    d *= d
    r2 = d @ np.ones(3)
    return (r2 < far * far) & (r2 > near * near)


def _rows(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``a[mask]`` for a C-contiguous (N, 3) float64 array, the same values, each row moved as one
    24-byte item (several times faster than numpy's row-wise boolean indexing)."""
    return a.view(np.dtype((np.void, 24))).ravel()[mask].view(np.float64).reshape(-1, 3)


def _fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane (unit n, d) with n.x + d = 0: the scatter matrix's weakest direction."""
    c = points.mean(axis=0)
    q = points - c
    n = np.linalg.eigh(q.T @ q)[1][:, 0]
    return n, -float(n @ c)


class LidarOdometry:
    """KISS-ICP odometry of ``base_link`` in ``map`` from a stream of :class:`LidarScan`."""

    def __init__(self, T_base_velodyne: np.ndarray, config: LidarOdometryConfig | None = None):
        from kiss_icp.kiss_icp import KissICP

        self._init_state(T_base_velodyne, config)
        self._icp = KissICP(self.config.to_kiss())

    @classmethod
    def follower(cls, T_base_velodyne: np.ndarray, config: LidarOdometryConfig | None = None) -> "LidarOdometry":
        """An odometry that registers nothing itself and follows one that runs elsewhere (another
        process) with the same ``T_base_velodyne`` and ``config``: each ``process(scan)`` takes the
        next of that one's :meth:`step` records given to :meth:`feed` (one per scan, in order), after
        which ``pose_at``, ``trajectory``, ``last_stamp``, ``floor_plane_map`` and ``stats`` answer
        with the same bits as it does."""
        from collections import deque

        self = cls.__new__(cls)
        self._init_state(T_base_velodyne, config)
        self._icp = None
        self._fed = deque()
        return self

    def _init_state(self, T_base_velodyne: np.ndarray, config: LidarOdometryConfig | None) -> None:
        self.config = config or LidarOdometryConfig()
        self.T_base_velodyne = np.asarray(T_base_velodyne, dtype=float).copy()
        if self.T_base_velodyne.shape != (4, 4):
            raise ValueError(f"T_base_velodyne must be 4x4, got {self.T_base_velodyne.shape}")
        self._T_velodyne_base = inv(self.T_base_velodyne)
        self._track = PoseTrack()  # T_map_base per registered scan
        # sensor velocity arriving at a pose (zero at the first): what extrapolation before the first
        # pose (the second pose's) and after the last (the last pose's) uses
        self._twist_early: list[np.ndarray] = []  # at the first two poses
        self._twist_last: np.ndarray | None = None
        self._T_v0_v = np.eye(4)  # last sensor pose in KISS-ICP's frame (velodyne at the first scan)
        self._twist = np.zeros(6)  # sensor body velocity (v, omega) per second
        self._period: float | None = None  # last observed time between poses
        self._floor: tuple[np.ndarray, float] | None = None  # floor plane (n, d), n.x + d = 0, KISS frame
        self.last_points_base: np.ndarray | None = None  # deskewed, voxelized points of the last scan
        self.stats = OdometryStats()
        self._last_step: tuple[float, np.ndarray] | None = None  # the last process() call's new pose, if any

    # ------------------------------------------------------------------ main entry

    def process(self, scan: LidarScan) -> np.ndarray | None:
        """Register one sweep; returns ``T_map_base`` at the middle of the sweep, or None if skipped."""
        if self._icp is None:
            return self._follow()
        t_start = time.perf_counter()
        self.stats.scans_in += 1
        self._last_step = None
        try:
            return self._process(scan)
        finally:
            self.stats.seconds += time.perf_counter() - t_start

    def step(self) -> dict:
        """What the last :meth:`process` call changed, as plain JSON values (floats round-trip
        exactly), for a :meth:`follower` elsewhere: the new pose (``stamp``, ``pose`` as 16 numbers,
        the sensor's ``twist`` then; all None when the scan was skipped), the floor plane and the
        counters."""
        stamp, pose = self._last_step if self._last_step is not None else (None, None)
        return {"stamp": stamp, "pose": None if pose is None else pose.ravel().tolist(),
                "twist": None if pose is None else self._twist_last.tolist(),
                "floor": None if self._floor is None else [*self._floor[0].tolist(), self._floor[1]],
                "stats": dict(vars(self.stats))}

    def feed(self, step: dict, points_base: np.ndarray | None = None) -> None:
        """A :meth:`follower`'s next scan, as the odometry it follows registered it: that one's
        :meth:`step` after the scan, and ``points_base``, its ``last_points_base`` where the caller
        needs them (else None here)."""
        self._fed.append((step, points_base))

    def _follow(self) -> np.ndarray | None:
        """The next fed step taken: the pose it registered (None where it skipped the scan)."""
        if not getattr(self, "_fed", None):
            raise RuntimeError("LidarOdometry.follower(): process(scan) before its step was fed")
        step, points_base = self._fed.popleft()
        self.stats = OdometryStats(**step["stats"])
        floor = step["floor"]
        self._floor = None if floor is None else (np.asarray(floor[:3], dtype=float), float(floor[3]))
        self.last_points_base = points_base
        if step["pose"] is None:
            return None
        T = np.asarray(step["pose"], dtype=float).reshape(4, 4)
        twist = np.asarray(step["twist"], dtype=float)
        self._track.append(float(step["stamp"]), T)
        if len(self._twist_early) < 2:
            self._twist_early.append(twist.copy())
        self._twist_last = twist
        return T

    def _process(self, scan: LidarScan) -> np.ndarray | None:
        points, times = self._clean(scan)
        if points is None:
            return None
        t_ref = float(scan.stamp + (0.5 * (times.min() + times.max()) if times.size else 0.0))
        sweep_s = float(np.ptp(times)) if times.size else 0.0

        dt = None if not self._track else t_ref - float(self._track.stamps[-1])
        if dt is not None and dt <= 0:
            log.warning("scan at %.6f s is not after the previous pose (%.6f s): time went backwards or "
                        "repeated; scan skipped", t_ref, float(self._track.stamps[-1]))
            self.stats.skipped_time += 1
            return None
        twist = self._twist
        horizon = dt or 0.0  # how far ahead the constant-velocity prediction reaches
        if dt is not None and dt > self.config.max_gap_s:
            log.warning("time jump of %.3f s before scan at %.6f s (over max_gap_s=%.3f): predicting with "
                        "constant velocity over %.3f s only; the pose may be wrong", dt, t_ref,
                        self.config.max_gap_s, self.config.max_gap_s)
            self.stats.time_jumps += 1
            horizon = self.config.max_gap_s
        elif dt is not None and self._period is not None and dt > self.config.gap_factor * self._period:
            log.warning("gap of %.3f s (~%.0f sweeps) before scan at %.6f s: dropped scans, predicting with "
                        "constant velocity", dt, dt / self._period, t_ref)
            self.stats.gaps += 1

        # Deskew with the predicted motion over this sweep (into the sensor frame at its middle), then
        # crop to the range limits as KISS-ICP does, about the sensor at the sweep's end.
        if self.config.deskew and times.size:
            frame = deskew_to_middle(points, times, twist * sweep_s)
            end = se3_exp(0.5 * twist * sweep_s)[:3, 3]  # the sensor at the sweep's end, from its middle
        else:
            frame, end = points, np.zeros(3)
        keep = _in_range(frame, end, self.config.min_range_m, self.config.max_range_m)
        if not keep.all():
            frame = _rows(frame, keep)
        if len(frame) < self.config.min_points:
            log.warning("scan at %.6f s has %d points within %.2f-%.2f m (min_points=%d): skipped",
                        t_ref, len(frame), self.config.min_range_m, self.config.max_range_m,
                        self.config.min_points)
            self.stats.skipped_few_points += 1
            return None

        prediction = self._T_v0_v @ se3_exp(twist * horizon)
        ground = None
        if self.config.floor_constraint:
            if self._floor is None and not self._track:
                self._floor = self._find_floor(frame)
            if self._floor is not None:
                ground = self._ground_mask(frame, prediction)
                if len(frame) - ground.sum() < self.config.min_points:
                    ground = None  # too little structure besides the floor: register everything

        registered = frame if ground is None else _rows(frame, ~ground)
        source, frame_downsample = self._icp.voxelize(registered)
        sigma = self._icp.adaptive_threshold.get_threshold()
        new_pose = self._icp.registration.align_points_to_map(
            points=source, voxel_map=self._icp.local_map, initial_guess=prediction,
            max_correspondance_distance=3 * sigma, kernel=sigma)
        if ground is not None and self._track:
            new_pose = self._level_on_floor(new_pose, _rows(frame, ground), t_ref)
        model_deviation = inv(prediction) @ new_pose
        if self._track and np.linalg.norm(model_deviation[:3, 3]) > self.config.max_correction_m:
            log.warning("scan at %.6f s: ICP moved the prediction by %.2f m (max_correction_m=%.2f); "
                        "the pose may be wrong", t_ref, np.linalg.norm(model_deviation[:3, 3]),
                        self.config.max_correction_m)
            self.stats.large_corrections += 1
        self._icp.adaptive_threshold.update_model_deviation(model_deviation)
        self._icp.local_map.update(frame_downsample, new_pose)

        if dt is not None:
            self._twist = se3_log(inv(self._T_v0_v) @ new_pose) / dt  # over a gap: its average velocity
            if self._period is None or dt <= self.config.gap_factor * self._period:
                self._period = dt
        self._T_v0_v = new_pose
        # keep KISS-ICP's own state consistent, for anyone reading it
        self._icp.last_pose, self._icp.last_delta = new_pose, se3_exp(self._twist * (self._period or 0.0))

        T_map_base = self.T_base_velodyne @ new_pose @ self._T_velodyne_base
        self._track.append(t_ref, T_map_base)
        if len(self._twist_early) < 2:
            self._twist_early.append(self._twist.copy())
        self._twist_last = self._twist.copy()
        self._last_step = (t_ref, T_map_base)
        self.last_points_base = frame_downsample @ self.T_base_velodyne[:3, :3].T + self.T_base_velodyne[:3, 3]
        self.stats.scans_used += 1
        return T_map_base

    # ------------------------------------------------------------------ the floor
    #
    # A spinning LiDAR draws the floor as rings centred on the sensor. The rings move with the robot,
    # so point-to-point ICP matches each ring to the same ring in the map and pulls a slowly moving
    # robot back towards where it was (measured: 23 % translation drift at 0.25 m/s). Without the floor,
    # nothing but the sensor-fixed scan lines on walls holds height and tilt, which then drift. So on a
    # flat floor the floor points are left out of ICP, and after ICP the pose's height, roll and pitch
    # are set so that this scan's floor plane coincides with the first scan's; x, y and yaw stay ICP's.

    def _find_floor(self, frame: np.ndarray) -> tuple[np.ndarray, float] | None:
        """The floor in the first scan: the largest near-horizontal plane below the sensor (RANSAC)."""
        up_s = self._T_velodyne_base[:3, :3] @ np.array([0.0, 0.0, 1.0])  # base z in the sensor frame
        r = np.linalg.norm(frame, axis=1)
        below = frame[(frame @ up_s) < -np.sin(np.radians(3.0)) * r]
        if len(below) < self.config.min_ground_points:
            log.warning("first scan: only %d points below the horizon; no floor constraint", len(below))
            return None
        rng = np.random.default_rng(0)
        best, best_count = None, 0
        for _ in range(100):
            a, b, c = below[rng.choice(len(below), 3, replace=False)]
            n = np.cross(b - a, c - a)
            if np.linalg.norm(n) < 1e-9:
                continue
            n /= np.linalg.norm(n)
            if abs(n @ up_s) < np.cos(np.radians(10.0)):
                continue
            count = int(np.count_nonzero(np.abs((below - a) @ n) < 0.03))
            if count > best_count:
                best, best_count = (n, -float(n @ a)), count
        if best is None or best_count < self.config.min_ground_points:
            log.warning("first scan: no floor plane with %d points found; no floor constraint",
                        self.config.min_ground_points)
            return None
        n, d = best
        plane = _fit_plane(below[np.abs(below @ n + d) < 0.03])
        n, d = plane if plane[0] @ up_s > 0 else (-plane[0], -plane[1])
        log.info("floor plane: %.3f m below the sensor, tilted %.2f deg from base_link z", d,
                 np.degrees(np.arccos(np.clip(n @ up_s, -1, 1))))
        return n, d  # the first scan's sensor frame is the KISS-ICP frame

    def _ground_mask(self, frame: np.ndarray, T_v0_v: np.ndarray) -> np.ndarray:
        n0, d0 = self._floor
        n_s = T_v0_v[:3, :3].T @ n0
        d_s = d0 + n0 @ T_v0_v[:3, 3]
        return np.abs(frame @ n_s + d_s) < self.config.ground_band_m

    def _level_on_floor(self, T_v0_v: np.ndarray, ground: np.ndarray, t_ref: float) -> np.ndarray:
        if len(ground) < self.config.min_ground_points:
            return T_v0_v
        n_s, d_s = _fit_plane(ground)
        n_s, d_s = _fit_plane(ground[np.abs(ground @ n_s + d_s) < 0.03]) if len(ground) > 3 else (n_s, d_s)
        R, t = T_v0_v[:3, :3], T_v0_v[:3, 3]
        n_c = R @ n_s
        d_c = d_s - n_c @ t
        n0, d0 = self._floor
        if n_c @ n0 < 0:
            n_c, d_c = -n_c, -d_c
        axis = np.cross(n_c, n0)
        angle = np.arctan2(np.linalg.norm(axis), n_c @ n0)
        if np.degrees(angle) > self.config.max_floor_correction_deg:
            log.warning("scan at %.6f s: floor plane %.1f deg off the first scan's (max_floor_correction_deg="
                        "%.1f); not levelled", t_ref, np.degrees(angle), self.config.max_floor_correction_deg)
            return T_v0_v
        R_c = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix() if angle > 0 else np.eye(3)
        shift = (d_c + n_c @ t - n0 @ t) - d0  # rotate about the sensor, then slide along the floor normal
        out = np.eye(4)
        out[:3, :3] = R_c @ R
        out[:3, 3] = t + shift * n0
        return out

    def _clean(self, scan: LidarScan) -> tuple[np.ndarray | None, np.ndarray]:
        """Finite float64 points and their times (empty times: no deskew for this scan)."""
        points = np.asarray(scan.points, dtype=np.float64).reshape(-1, 3) if scan.points is not None \
            else np.empty((0, 3))
        times = np.asarray(scan.times_s, dtype=np.float64).ravel() if scan.times_s is not None else None
        if times is None or len(times) != len(points):
            if self.config.deskew and len(points):
                log.warning("scan at %.6f s: %s per-point times for %d points; not deskewed",
                            scan.stamp, "no" if times is None else len(times), len(points))
            times = None
        if np.isfinite(points.sum()) and (times is None or np.isfinite(times.sum())):
            bad = 0  # a finite sum: every value is finite (else, also where a sum overflows, each is checked)
        else:
            ok = np.all(np.isfinite(points), axis=1)
            if times is not None:
                ok &= np.isfinite(times)
            bad = int(len(points) - ok.sum())
        if bad:
            self.stats.nonfinite_points += bad
            log.warning("scan at %.6f s: dropped %d of %d points with non-finite coordinates or times",
                        scan.stamp, bad, len(points))
            points = points[ok]
            times = times[ok] if times is not None else None
        if len(points) < self.config.min_points:
            log.warning("scan at %.6f s has %d usable points (min_points=%d): skipped",
                        scan.stamp, len(points), self.config.min_points)
            self.stats.skipped_few_points += 1
            return None, np.empty(0)
        if times is None or np.ptp(times) <= 0:
            times = np.empty(0)
        return np.ascontiguousarray(points), times

    # ------------------------------------------------------------------ queries

    def __len__(self) -> int:
        return len(self._track)

    def floor_plane_map(self) -> tuple[np.ndarray, float] | None:
        """The floor the first scan found, in ``map``: (unit normal n pointing up, d) with n.x + d = 0
        on the floor, so n.x + d is a point's height above it. None without a floor constraint."""
        if self._floor is None:
            return None
        n0, d0 = self._floor  # the first scan's sensor frame
        n = self.T_base_velodyne[:3, :3] @ n0
        return n, float(d0 - n @ self.T_base_velodyne[:3, 3])

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (N,), T_map_base (N, 4, 4)) of every registered scan."""
        return self._track.arrays()

    def last_stamp(self) -> float | None:
        """The newest registered pose's stamp (None before any)."""
        return float(self._track.stamps[-1]) if self._track else None

    def pose_at(self, t: float) -> np.ndarray | None:
        """``T_map_base`` at time t: SE(3) interpolation between scans; constant-velocity extrapolation
        up to ``max_extrapolation_s`` past either end; None when further out or before any scan."""
        if not self._track:
            return None
        stamps, poses = self._track.stamps, self._track.poses
        t0, t1 = float(stamps[0]), float(stamps[-1])
        lim = self.config.max_extrapolation_s
        if t < t0 - lim or t > t1 + lim:
            return None
        if t0 <= t <= t1:
            return interpolate_trajectory(stamps, poses, t)
        # velocity is per second in the sensor frame; conjugate into base_link
        i = 0 if t < t0 else -1
        twist = self._twist_early[-1] if i == 0 else self._twist_last
        twist_base = se3_log(self.T_base_velodyne @ se3_exp(twist) @ self._T_velodyne_base)
        return poses[i] @ se3_exp(twist_base * (t - float(stamps[i])))


class WheelOdometryTrack:
    """Wheel odometry re-expressed like the LiDAR odometry: ``T_map_base`` with ``map`` = base at the first message."""

    def __init__(self):
        self._track = PoseTrack()
        self._T_base0_odom: np.ndarray | None = None

    def add(self, msg: WheelOdometry) -> np.ndarray:
        if self._track and msg.stamp <= self._track.stamps[-1]:
            log.warning("wheel odometry at %.6f s is not after the previous one (%.6f s): ignored",
                        msg.stamp, float(self._track.stamps[-1]))
            return self._track.poses[-1].copy()
        if self._T_base0_odom is None:
            self._T_base0_odom = inv(np.asarray(msg.T_odom_base, dtype=float))
        T = self._T_base0_odom @ msg.T_odom_base
        self._track.append(float(msg.stamp), T)
        return T

    def __len__(self) -> int:
        return len(self._track)

    @property
    def stamps(self) -> np.ndarray:
        """The stamps so far (a read-only view)."""
        return self._track.stamps

    @property
    def poses(self) -> np.ndarray:
        """The poses so far, (N, 4, 4) (a read-only view)."""
        return self._track.poses

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        return self._track.arrays()

    def pose_at(self, t) -> np.ndarray:
        """Interpolated (clamped at the ends) pose(s) at t."""
        if not self._track:
            raise ValueError("no wheel odometry yet")
        return interpolate_trajectory(self._track.stamps, self._track.poses, t)
