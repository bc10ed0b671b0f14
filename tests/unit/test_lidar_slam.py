"""LiDAR odometry (real KISS-ICP) on synthetic sweeps ray-cast in a box room with pillars and furniture.

The ray caster below is independent of ``sim``: a 32-beam sweep of 1808 columns whose columns fire
at their own times from the sensor pose at that time (motion skew), with 1 cm range noise.
"""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from stack import metrics
from stack.config import ConfigError, resolve_config
from stack.lidar_slam import (LidarOdometry, LidarOdometryConfig, WheelOdometryTrack, deskew_to_middle, se3_exp,
                              se3_log)
from stack.messages import LidarScan, WheelOdometry
from stack.transforms import from_xyz_rpy, interpolate, make_T

# --------------------------------------------------------------------------------------------
# synthetic world

VERTICAL_DEG = [-25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0,
                -2.667, -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333,
                1.667, 2.333, 3.333, 4.667, 7.0, 10.333, 15.0]
ROOM = np.array([[-7.0, -5.0, 0.0], [7.0, 5.0, 2.6]])  # inside of a box: floor, walls, ceiling
BOXES = [  # (min corner, max corner): pillars and furniture
    ([2.0, 1.5, 0.0], [2.4, 1.9, 2.6]), ([-1.0, 2.5, 0.0], [-0.6, 2.9, 2.6]), ([4.5, -3.0, 0.0], [4.9, -2.6, 2.6]),
    ([-5.5, 3.0, 0.0], [-4.5, 4.2, 0.75]), ([0.5, -4.6, 0.0], [2.5, -4.0, 1.8]), ([-6.5, -4.5, 0.0], [-6.0, -1.0, 1.2]),
    ([5.5, 2.0, 0.0], [6.2, 4.0, 0.9]),
]
BASE_Z = 0.0635  # base_link above the floor
T_BASE_VELODYNE = make_T(t=[0.0, 0.0, 0.384])
PERIOD = 0.1
AZIMUTH_STEPS = 1808


def cast(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Range along each ray (N,) to the first surface: the room's inside or a box's outside (slab test)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_d = 1.0 / dirs
        best = np.full(len(origins), np.inf)
        for k in range(3):  # leaving the room through the wall, floor or ceiling ahead
            wall = np.where(inv_d[:, k] > 0, ROOM[1, k], ROOM[0, k])
            np.minimum(best, (wall - origins[:, k]) * inv_d[:, k], out=best)
        for lo, hi in BOXES:
            t_in, t_out = np.full(len(origins), -np.inf), np.full(len(origins), np.inf)
            for k in range(3):
                a, b = (lo[k] - origins[:, k]) * inv_d[:, k], (hi[k] - origins[:, k]) * inv_d[:, k]
                np.maximum(t_in, np.minimum(a, b), out=t_in)
                np.minimum(t_out, np.maximum(a, b), out=t_out)
            hit = (t_out >= t_in) & (t_in > 0) & (t_in < best)
            best[hit] = t_in[hit]
    return best


class Drive:
    """A unicycle drive (forward speed v, yaw rate w(t)) integrated at 1 kHz; ground truth of base_link."""

    def __init__(self, duration: float, v: float = 0.6, w_amp: float = 0.5, start=(-4.0, -2.0, 0.0)):
        dt = 1e-3
        self.t = np.arange(0.0, duration + 1.0, dt)
        ramp = np.clip(self.t / 1.0, 0.0, 1.0)  # start from rest
        w = w_amp * np.sin(0.4 * self.t) * ramp
        self.yaw = start[2] + np.concatenate([[0.0], np.cumsum(w[:-1] * dt)])
        self.x = start[0] + np.concatenate([[0.0], np.cumsum((v * ramp * np.cos(self.yaw))[:-1] * dt)])
        self.y = start[1] + np.concatenate([[0.0], np.cumsum((v * ramp * np.sin(self.yaw))[:-1] * dt)])

    def T_world_base(self, t) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        x, y, yaw = (np.interp(t, self.t, a) for a in (self.x, self.y, self.yaw))
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
        T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = x, y, BASE_Z
        return T

    def scan(self, stamp: float, rng: np.random.Generator) -> LidarScan:
        col_t = np.arange(AZIMUTH_STEPS) * PERIOD / AZIMUTH_STEPS
        az = np.pi - 2 * np.pi * np.arange(AZIMUTH_STEPS) / AZIMUTH_STEPS
        el = np.radians(VERTICAL_DEG)[None, :]
        dirs = np.stack([np.cos(el) * np.cos(az)[:, None], np.cos(el) * np.sin(az)[:, None],
                         np.sin(el) * np.ones((AZIMUTH_STEPS, 1))], axis=-1)  # (A, R, 3) sensor frame
        T_ws = self.T_world_base(stamp + col_t) @ T_BASE_VELODYNE  # sensor pose at each column's firing
        d_world = np.einsum("aij,arj->ari", T_ws[:, :3, :3], dirs)
        o_world = np.broadcast_to(T_ws[:, None, :3, 3], d_world.shape)
        r = cast(o_world.reshape(-1, 3), d_world.reshape(-1, 3)).reshape(d_world.shape[:2])
        r = r + rng.normal(0.0, 0.01, r.shape)
        ok = np.isfinite(r) & (r > 0.4)
        times = np.broadcast_to(col_t[:, None], r.shape)[ok]
        return LidarScan(stamp, (dirs * r[..., None])[ok].astype(np.float32), times.copy(),
                         T_world_sensor=T_ws[0])


def test_ray_caster_hits_the_surfaces():
    drive = Drive(2.0)
    s = drive.scan(1.0, np.random.default_rng(0))
    T_ws = drive.T_world_base(s.stamp + s.times_s) @ T_BASE_VELODYNE
    p = np.einsum("nij,nj->ni", T_ws[:, :3, :3], s.points.astype(float)) + T_ws[:, :3, 3]
    d = np.min(np.abs(np.concatenate([p - ROOM[0], p - ROOM[1]], axis=1)), axis=1)
    for lo, hi in BOXES:
        d = np.where(np.all((p > np.asarray(lo) - 0.05) & (p < np.asarray(hi) + 0.05), axis=1), 0.0, d)
    assert len(p) > 50_000
    assert np.percentile(d, 99) < 0.04  # on a surface, up to the 1 cm range noise


DURATION = 4.0


@pytest.fixture(scope="module")
def drive_and_scans():
    drive = Drive(DURATION)
    rng = np.random.default_rng(0)
    return drive, [drive.scan(i * PERIOD, rng) for i in range(int(DURATION / PERIOD))]


def run(scans, config: LidarOdometryConfig | None = None, T_base_velodyne=T_BASE_VELODYNE) -> LidarOdometry:
    odo = LidarOdometry(T_base_velodyne, config)
    for s in scans:
        odo.process(s)
    return odo


def score(drive: Drive, odo: LidarOdometry) -> tuple[float, metrics.RPEResult]:
    stamps, T_map_base = odo.trajectory()
    gt = drive.T_world_base(stamps)
    est = gt[0] @ T_map_base  # the known start pose places map in world
    return metrics.ate_rmse(est, gt), metrics.rpe(est, gt, delta_m=1.0)


@pytest.fixture(scope="module")
def reference_run(drive_and_scans):
    drive, scans = drive_and_scans
    return run(scans)


# --------------------------------------------------------------------------------------------
# accuracy


def test_tracks_a_skewed_drive(drive_and_scans, reference_run):
    drive, scans = drive_and_scans
    odo = reference_run
    assert len(odo) == len(scans)
    stamps, _ = odo.trajectory()
    # a pose is stamped at the middle of its sweep, where the sweep is deskewed to
    np.testing.assert_allclose(stamps, [s.stamp + 0.5 * (s.times_s.min() + s.times_s.max()) for s in scans])
    ate, rpe = score(drive, odo)
    assert ate < 0.03
    assert rpe.trans_pct < 1.0 and rpe.rot_deg_per_m < 0.5


def test_deskew_matters(drive_and_scans, reference_run):
    drive, scans = drive_and_scans
    _, rpe_on = score(drive, reference_run)
    _, rpe_off = score(drive, run(scans, LidarOdometryConfig(deskew=False)))
    assert rpe_off.trans_pct > 1.5 * rpe_on.trans_pct


def test_pose_at_interpolates_and_extrapolates_a_little(drive_and_scans, reference_run):
    drive, _ = drive_and_scans
    odo = reference_run
    stamps, poses = odo.trajectory()
    np.testing.assert_allclose(odo.pose_at(stamps[7]), poses[7], atol=1e-12)
    mid = 0.5 * (stamps[7] + stamps[8])
    np.testing.assert_allclose(odo.pose_at(mid), interpolate(poses[7], poses[8], 0.5), atol=1e-9)
    T_world_map = drive.T_world_base(stamps[0])[0]
    for t in (mid, stamps[-1] + 0.1, stamps[0] - 0.05):  # inside, and constant velocity past the ends
        err = np.linalg.norm((T_world_map @ odo.pose_at(t))[:3, 3] - drive.T_world_base(t)[0][:3, 3])
        assert err < 0.03, t
    assert odo.pose_at(stamps[-1] + 1.0) is None
    assert odo.pose_at(stamps[0] - 1.0) is None
    assert LidarOdometry(T_BASE_VELODYNE).pose_at(0.0) is None


def test_a_follower_fed_each_step_answers_with_the_same_bits(drive_and_scans):
    """An odometry registering elsewhere (another process) hands each scan's ``step()`` over as JSON;
    a follower fed them answers every query as the one that registered, bit for bit, skipped scans,
    extrapolation past both ends and the floor included."""
    import json

    _, scans = drive_and_scans
    empty = LidarScan(scans[3].stamp + 0.01, np.empty((0, 3), np.float32), np.empty(0))
    stream = scans[:3] + [empty] + scans[3:15] + [scans[10]]  # a skipped scan, and an old one again
    odo = LidarOdometry(T_BASE_VELODYNE)
    follower = LidarOdometry.follower(T_BASE_VELODYNE)
    with pytest.raises(RuntimeError, match="fed"):
        follower.process(scans[0])
    for scan in stream:
        pose = odo.process(scan)
        follower.feed(json.loads(json.dumps(odo.step())), odo.last_points_base if pose is not None else None)
        got = follower.process(LidarScan(scan.stamp, np.empty((0, 3)), np.empty(0)))
        assert (got is None) == (pose is None)
        if pose is not None:
            assert got.tobytes() == pose.tobytes()
            assert follower.last_points_base is odo.last_points_base or \
                follower.last_points_base.tobytes() == odo.last_points_base.tobytes()
        assert follower.last_stamp() == odo.last_stamp()
    (s1, p1), (s2, p2) = odo.trajectory(), follower.trajectory()
    assert len(s1) == 15 and s1.tobytes() == s2.tobytes() and p1.tobytes() == p2.tobytes()
    for t in (s1[0] - 0.1, s1[0] - 0.01, s1[0], 0.5 * (s1[4] + s1[5]), s1[-1], s1[-1] + 0.05, s1[-1] + 0.19,
              s1[-1] + 1.0):
        a, b = odo.pose_at(t), follower.pose_at(t)
        assert (a is None and b is None) or a.tobytes() == b.tobytes(), t
    n1, d1 = odo.floor_plane_map()
    n2, d2 = follower.floor_plane_map()
    assert n1.tobytes() == n2.tobytes() and d1 == d2
    assert vars(follower.stats) == vars(odo.stats)
    assert odo.stats.skipped_few_points == 1 and odo.stats.skipped_time == 1


# --------------------------------------------------------------------------------------------
# robustness: every case warns and has a defined outcome


def _warned(caplog, text: str) -> bool:
    return any(r.levelno == logging.WARNING and text in r.getMessage() for r in caplog.records)


def test_empty_and_tiny_scans_are_skipped(drive_and_scans, caplog):
    _, scans = drive_and_scans
    odo = run(scans[:3])
    empty = LidarScan(0.35, np.empty((0, 3), np.float32), np.empty(0))
    tiny = LidarScan(0.36, scans[3].points[:20], scans[3].times_s[:20])
    with caplog.at_level(logging.WARNING):
        assert odo.process(empty) is None
        assert odo.process(tiny) is None
    assert _warned(caplog, "usable points")
    assert len(odo) == 3 and odo.stats.skipped_few_points == 2
    assert odo.process(scans[3]) is not None  # carries on


def test_nan_laden_scan_is_cleaned(drive_and_scans, caplog):
    drive, scans = drive_and_scans
    rng = np.random.default_rng(1)
    dirty = []
    for s in scans[:20]:
        pts = s.points.copy()
        pts[rng.random(len(pts)) < 0.3] = np.nan
        times = s.times_s.copy()
        times[rng.random(len(times)) < 0.01] = np.inf
        dirty.append(LidarScan(s.stamp, pts, times))
    with caplog.at_level(logging.WARNING):
        odo = run(dirty)
    assert _warned(caplog, "non-finite")
    assert len(odo) == 20 and odo.stats.nonfinite_points > 0.3 * 20 * 50_000
    ate, _ = score(drive, odo)
    assert ate < 0.03
    all_nan = LidarScan(2.05, np.full((1000, 3), np.nan, np.float32), np.zeros(1000))
    assert odo.process(all_nan) is None


def test_missing_point_times_register_without_deskew(drive_and_scans, caplog):
    _, scans = drive_and_scans
    odo = run(scans[:5])
    s = scans[5]
    with caplog.at_level(logging.WARNING):
        assert odo.process(LidarScan(s.stamp, s.points, s.times_s[:10])) is not None
    assert _warned(caplog, "not deskewed")
    assert odo.trajectory()[0][-1] == s.stamp  # no per-point times: the pose is at the stamp


def test_dropped_scans_use_constant_velocity(drive_and_scans, caplog):
    drive, scans = drive_and_scans
    kept = scans[:15] + scans[19:30]  # 0.4 s of sweeps lost
    with caplog.at_level(logging.WARNING):
        odo = run(kept)
    assert _warned(caplog, "dropped scans")
    assert odo.stats.gaps == 1 and len(odo) == len(kept)
    ate, _ = score(drive, odo)
    assert ate < 0.03


def test_time_going_backwards_skips_the_scan(drive_and_scans, caplog):
    _, scans = drive_and_scans
    odo = run(scans[:12])
    with caplog.at_level(logging.WARNING):
        assert odo.process(scans[10]) is None  # an old sweep again
        assert odo.process(scans[11]) is None  # the same stamp again
    assert _warned(caplog, "backwards")
    assert odo.stats.skipped_time == 2
    stamps, _ = odo.trajectory()
    assert np.all(np.diff(stamps) > 0) and len(stamps) == 12


def test_time_jump_extrapolates_only_max_gap(drive_and_scans, caplog):
    drive, scans = drive_and_scans
    kept = scans[:15] + scans[28:]  # 1.3 s missing, over max_gap_s = 1 s
    with caplog.at_level(logging.WARNING):
        odo = run(kept, LidarOdometryConfig(max_gap_s=1.0))
    assert _warned(caplog, "time jump")
    assert odo.stats.time_jumps == 1 and len(odo) == len(kept)
    # 1 s of constant velocity leaves 0.18 m for ICP to find
    ate, _ = score(drive, odo)
    assert ate < 0.03


# --------------------------------------------------------------------------------------------
# small parts


def test_se3_exp_log():
    xi = np.array([0.3, -0.1, 0.05, 0.2, -0.4, 1.1])
    np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, atol=1e-12)
    np.testing.assert_allclose(se3_exp([1, 2, 3, 0, 0, 0]), make_T(t=[1, 2, 3]))
    # a quarter turn about z while moving forward pi/2 * r: an arc of radius 1 ends at (1, 1)
    T = se3_exp([math.pi / 2, 0, 0, 0, 0, math.pi / 2])
    np.testing.assert_allclose(T[:3, 3], [1, 1, 0], atol=1e-12)


@pytest.mark.parametrize("turn", [0.0, 1e-12, 1e-6, 9.9e-4, 1.01e-3, 0.05, 1.0, 3.0])
def test_deskew_is_the_exponential_at_each_point(turn):
    """Each point moved by exp((s - 1/2) xi), s its time in [0, 1]: against the matrix exponential
    (scipy's expm of the twist's 4x4 matrix), on both sides of the small-rotation series."""
    from scipy.linalg import expm

    rng = np.random.default_rng(7)
    points = rng.normal(size=(5000, 3)) * 10  # more than one of the loop's chunks
    times = 0.02 + np.sort(rng.uniform(0.0, 0.1, len(points)))
    w = rng.normal(size=3)
    xi = np.concatenate([rng.normal(size=3) * 0.2, w / np.linalg.norm(w) * turn])
    X = np.zeros((4, 4))
    X[:3, :3] = [[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]]
    X[:3, 3] = xi[:3]
    s = (times - times.min()) / np.ptp(times)
    pick = np.r_[0, len(points) - 1, rng.choice(len(points), 60, replace=False)]
    want = np.array([(expm((s[i] - 0.5) * X) @ np.append(points[i], 1.0))[:3] for i in pick])
    got = deskew_to_middle(points, times, xi)
    np.testing.assert_allclose(got[pick], want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("turn", [0.0, 1e-4, 0.05, 1.0])
def test_deskew_and_crop_are_kiss_icps(turn):
    """KISS-ICP's own deskew (to the sweep's end) and range crop, then exp(xi / 2): the same points."""
    from kiss_icp.preprocess import get_preprocessor

    rng = np.random.default_rng(3)
    points = rng.normal(size=(20000, 3)) * 8
    times = np.repeat(np.linspace(0.0, 0.1, 2000), 10)
    xi = np.array([0.03, -0.004, 0.001, 0.0, 0.0, 0.0])
    xi[3:] = rng.normal(size=3) / np.sqrt(3) * turn
    config = LidarOdometryConfig()
    kiss = get_preprocessor(config.to_kiss()).preprocess(points, times, se3_exp(xi))
    half = se3_exp(0.5 * xi)
    kiss = kiss @ half[:3, :3].T + half[:3, 3]
    ours = deskew_to_middle(points, times, xi)
    d = np.linalg.norm(ours - half[:3, 3], axis=1)  # the range about the sensor at the sweep's end
    kept = (d > config.min_range_m) & (d < config.max_range_m)
    assert (d < config.min_range_m).any() and (d > config.max_range_m).any()  # cropped at both ends
    assert len(kiss) == kept.sum()
    np.testing.assert_allclose(ours[kept], kiss, rtol=0, atol=1e-9)


def test_config_defaults_yaml_and_errors(tmp_path):
    """The odometry's settings are the [odometry] section of the one config (stack.config)."""
    cfg = resolve_config().odometry
    assert cfg.max_range_m == 30.0 and cfg.min_range_m == 0.5 and cfg.deskew
    f = tmp_path / "odo.yaml"
    f.write_text("odometry:\n  voxel_size_m: 0.4\n  max_range_m: 20\n")
    cfg = resolve_config(f, ["odometry.min_range_m=0.3"], environ={}).odometry
    assert (cfg.voxel_size_m, cfg.max_range_m, cfg.min_range_m) == (0.4, 20.0, 0.3)
    assert cfg.to_kiss().mapping.voxel_size == 0.4
    f.write_text("odometry:\n  voxel_size_m: -1\n")
    with pytest.raises(ConfigError, match=r"odo\.yaml.*odometry\.voxel_size_m"):
        resolve_config(f, environ={})
    f.write_text("odometry:\n  voxel_size: 0.4\n")
    with pytest.raises(ConfigError, match=r"odometry\.voxel_size"):
        resolve_config(f, environ={})


def test_wheel_odometry_track_starts_at_identity(caplog):
    track = WheelOdometryTrack()
    track.add(WheelOdometry(1.0, from_xyz_rpy([1, 2, 0], [0, 0, math.pi / 2]), 0.0, 0.0))
    track.add(WheelOdometry(2.0, from_xyz_rpy([1, 3, 0], [0, 0, math.pi / 2]), 1.0, 0.0))
    stamps, poses = track.trajectory()
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(poses[1], make_T(t=[1, 0, 0]), atol=1e-12)  # odom +y was base0's +x
    np.testing.assert_allclose(track.pose_at(1.5)[:3, 3], [0.5, 0, 0], atol=1e-12)
    with caplog.at_level(logging.WARNING):
        track.add(WheelOdometry(1.5, np.eye(4), 0.0, 0.0))
    assert _warned(caplog, "not after") and len(track) == 2


def test_kiss_icp_in_a_child_process_gives_the_same_bits(drive_and_scans):
    """``dopeslam run`` registers its sweeps in a child process (:mod:`testbed.odometry_process`): the
    follower it feeds answers as KISS-ICP in this process does, bit for bit, skipped sweeps
    included; the registered points come back for the sweeps the pipeline draws into its map. A child
    that fails or dies is an error naming the odometry process, not a hang."""
    from testbed.odometry_process import OdometryProcess

    _, scans = drive_and_scans
    empty = LidarScan(scans[3].stamp + 0.01, np.empty((0, 3), np.float32), np.empty(0))
    stream = scans[:3] + [empty] + scans[3:12] + [scans[8]]
    odo = LidarOdometry(T_BASE_VELODYNE)
    kiss = OdometryProcess(T_BASE_VELODYNE, points_every=5)
    try:
        for scan in stream:
            kiss.submit(scan)
        assert kiss.in_flight == len(stream)
        registered = 0
        for scan in stream:
            assert kiss.take() is scan
            pose, got = odo.process(scan), kiss.odometry.process(scan)
            assert (got is None) == (pose is None)
            if pose is not None:
                registered += 1
                assert got.tobytes() == pose.tobytes()
                sent = kiss.odometry.last_points_base
                assert (sent is not None) == (registered % 5 == 1)
                assert sent is None or sent.tobytes() == odo.last_points_base.tobytes()
        assert registered == 12 and kiss.in_flight == 0
        (s1, p1), (s2, p2) = odo.trajectory(), kiss.odometry.trajectory()
        assert s1.tobytes() == s2.tobytes() and p1.tobytes() == p2.tobytes()
        for t in (s1[0] - 0.05, 0.5 * (s1[2] + s1[3]), s1[-1] + 0.1):
            assert odo.pose_at(t).tobytes() == kiss.odometry.pose_at(t).tobytes()
        assert kiss.odometry.stats.skipped_few_points == odo.stats.skipped_few_points == 1
    finally:
        kiss.close()
    kiss = OdometryProcess(T_BASE_VELODYNE)
    kiss.submit(LidarScan(1.0, np.zeros((1000, 2)), np.zeros(1000)))  # 2000 numbers are not (N, 3) points
    with pytest.raises(RuntimeError, match=r"^odometry process: ValueError"):
        kiss.take()
    kiss = OdometryProcess(T_BASE_VELODYNE)
    kiss._proc.kill()
    kiss._proc.wait()
    kiss.submit(scans[0])
    with pytest.raises(RuntimeError, match="^odometry process: it exited"):
        kiss.take()
    assert kiss._proc is None
