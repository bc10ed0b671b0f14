"""Scripted drive-through episodes: route following through the physics, frame order and ground truth,
and determinism of ``dopeslam simulate``."""
from __future__ import annotations

import json

import numpy as np
import pytest

from sim.episode import Episode
from sim.scenario import load_scenario
from stack.messages import CameraFrame, LidarScan, WheelOdometry
from stack.transforms import inv
from testbed.cli import main as cli_main


def test_robot_follows_the_default_route_within_10_cm_of_its_waypoints():
    sc = load_scenario(None)
    with Episode(sc, seed=0, camera=False, lidar=False) as ep:  # the whole 60 s: physics only
        odometry = [m for m in ep.frames() if isinstance(m, WheelOdometry)]
        follower, gt = ep.follower, ep.groundtruth
    assert follower.done
    assert len(follower.closest) == len(sc.route.waypoints)
    assert np.all(follower.closest < 0.10), follower.closest
    xy, t = gt.T_world_base[:, :2, 3], gt.stamps
    # still for the start pause, then driving no faster than the route's speed
    still = t < sc.route.start_pause
    assert np.linalg.norm(xy[still] - xy[0], axis=1).max() < 0.01
    speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / np.diff(t)
    assert speed.max() < sc.route.speed * 1.1
    assert np.linalg.norm(xy[-1] - sc.route.waypoints[-1][:2]) < 0.10
    # wheel odometry tracks the path but drifts (it is not a copy of the ground truth)
    assert len(odometry) == pytest.approx(sc.duration * sc.sensors.wheel_odometry_rate, abs=1)
    T_start = gt.T_world_base[0]
    true_rel = inv(T_start) @ gt.T_world_base[-1]
    err = np.linalg.norm(odometry[-1].T_odom_base[:3, 3] - true_rel[:3, 3])
    path = np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()
    assert path > 6.0
    assert 1e-4 < err < 0.2 * path


def test_frames_come_in_time_order_with_their_ground_truth_poses():
    sc = load_scenario(None)
    sc = sc.model_copy(update={"route": sc.route.model_copy(update={"start_pause": 0.0})})  # drive at once
    duration = 0.35
    with Episode(sc, seed=0, duration=duration) as ep:
        frames = list(ep.frames())
        # in the order the data becomes available: a scan when its sweep ends (it is stamped at the start)
        ready = [m.stamp + (ep.beams.period if isinstance(m, LidarScan) else 0.0) for m in frames]
        assert ready == sorted(ready)
        kinds = {k: [m for m in frames if isinstance(m, k)] for k in (LidarScan, CameraFrame, WheelOdometry)}
        assert len(kinds[LidarScan]) == 3  # full sweeps end at 0.1, 0.2, 0.3 s
        assert len(kinds[CameraFrame]) == 4  # 0.0, 0.1, 0.2, 0.3 s
        assert len(kinds[WheelOdometry]) == 8  # 20 Hz, 0.0 .. 0.35 s
        for scan in kinds[LidarScan]:
            np.testing.assert_allclose(scan.T_world_sensor, ep.T_world_base_at(scan.stamp) @ ep.T_base_velodyne,
                                       atol=1e-9)
        for frame in kinds[CameraFrame]:
            np.testing.assert_allclose(frame.T_world_camera, ep.T_world_base_at(frame.stamp) @ ep.T_base_camera,
                                       atol=1e-9)
            assert frame.rgb.shape == (480, 640, 3) and frame.depth_m.shape == (480, 640)
            assert frame.info.width == 640 and frame.info.fx == pytest.approx(610.0)
        # map = base_link at the first scan's stamp (the start of its sweep)
        np.testing.assert_allclose(ep.T_world_map, ep.T_world_base_at(kinds[LidarScan][0].stamp), atol=1e-9)
        assert np.linalg.norm(ep.groundtruth.T_world_base[-1, :2, 3] - ep.groundtruth.T_world_base[0, :2, 3]) > 0.01


def test_render_worker_gives_the_same_frames_in_the_same_order():
    sc = load_scenario(None)
    sc = sc.model_copy(update={"route": sc.route.model_copy(update={"start_pause": 0.0})})
    runs, rows = {}, {}
    for worker in (False, True, 2, 3):  # in the loop; one worker process; two and three, frames alternating
        with Episode(sc, seed=11, duration=0.45, render_worker=worker) as ep:
            runs[worker], rows[worker] = [], []
            for m in ep.frames():
                runs[worker].append(m)
                rows[worker].append(ep.groundtruth_rows if not isinstance(m, CameraFrame) else None)
    for worker in (True, 2, 3):
        assert [(type(m), m.stamp) for m in runs[False]] == [(type(m), m.stamp) for m in runs[worker]], worker
        assert rows[worker] == rows[True]  # the ground truth each message was made with
        frames = [(a, b) for a, b in zip(runs[False], runs[worker]) if isinstance(a, CameraFrame)]
        assert len(frames) == 5
        for a, b in frames:
            np.testing.assert_array_equal(a.rgb, b.rgb)
            np.testing.assert_array_equal(a.depth_m, b.depth_m)
            np.testing.assert_array_equal(a.extra["segmentation"], b.extra["segmentation"])
            np.testing.assert_array_equal(a.T_world_camera, b.T_world_camera)


class _EveryOther:
    """A camera demand wanting the 1st, 3rd, 5th... frame; it notes the messages it was shown."""

    def __init__(self):
        self.seen, self.asked = [], []

    def see(self, msg):
        self.seen.append((type(msg), msg.stamp))

    def wants(self, t):
        self.asked.append(t)
        return len(self.asked) % 2 == 1


@pytest.mark.parametrize("worker", [False, 2])
def test_frames_nobody_wants_are_not_rendered_and_the_rest_are_unchanged(worker):
    """``Episode.camera_demand``: a frame it does not want comes out in its place with its pose and no
    pixels; every other message, and every frame drawn, is the one drawn without a demand (each
    frame's noise seed is still drawn in frame order). The demand sees every other message before it
    is asked about a frame."""
    sc = load_scenario(None)
    sc = sc.model_copy(update={"route": sc.route.model_copy(update={"start_pause": 0.0})})
    runs = {}
    for demand in (None, _EveryOther()):
        with Episode(sc, seed=11, duration=0.85, render_worker=worker) as ep:
            ep.camera_demand = demand
            runs[demand is not None] = list(ep.frames())
            assert ep.unrendered_frames == (0 if demand is None else 4)
    full, some = runs[False], runs[True]
    assert [(type(m), m.stamp) for m in full] == [(type(m), m.stamp) for m in some]
    assert demand.seen == [(type(m), m.stamp) for m in full if not isinstance(m, CameraFrame)]
    assert demand.asked == [m.stamp for m in full if isinstance(m, CameraFrame)]
    frames = [(a, b) for a, b in zip(full, some) if isinstance(a, CameraFrame)]
    assert len(frames) == 9
    for i, (a, b) in enumerate(frames):
        np.testing.assert_array_equal(a.T_world_camera, b.T_world_camera)
        if i % 2:
            assert b.rgb is None and b.depth_m is None and b.extra == {"segmentation": None, "unrendered": True}
        else:
            np.testing.assert_array_equal(a.rgb, b.rgb)
            np.testing.assert_array_equal(a.depth_m, b.depth_m)
            np.testing.assert_array_equal(a.extra["segmentation"], b.extra["segmentation"])
    for a, b in zip(full, some):
        if isinstance(a, LidarScan):
            np.testing.assert_array_equal(a.points, b.points)


@pytest.mark.parametrize("workers", [1, 2])
def test_render_workers_draw_while_the_consumer_works(workers):
    """When a frame is handed out, every worker is already drawing a later one (but at the end), so
    the consumer's work on it overlaps the rendering."""
    sc = load_scenario(None)
    with Episode(sc, seed=5, duration=0.85, render_worker=workers) as ep:
        busy = [sum(w._in_flight for w in ep._render_workers) for m in ep.frames() if isinstance(m, CameraFrame)]
    assert len(busy) == 9
    assert busy[:-workers] == [workers] * (9 - workers)


def simulate(out, seed: int) -> dict:
    assert cli_main(["simulate", "--out", str(out), "--seed", str(seed), "--duration", "0.5"]) == 0
    return json.loads((out / "summary.json").read_text())


def test_simulate_is_deterministic_per_seed(tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    summary = simulate(a, 3)
    simulate(b, 3)
    simulate(c, 4)
    for key in ("sim_seconds", "wall_seconds", "real_time_factor", "camera_frames", "lidar_scans",
                "lidar_points_per_scan"):
        assert key in summary
    assert summary["camera_frames"] == 6 and summary["lidar_scans"] == 5
    assert summary["lidar_points_per_scan"] > 50_000
    images = sorted(p.name for p in a.glob("*.png") if p.name != "scene_topdown.png")
    assert any(n.startswith("rgb_") for n in images) and any(n.startswith("depth_") for n in images)
    assert (a / "scene_topdown.png").stat().st_size > 10_000
    assert images == sorted(p.name for p in b.glob("*.png") if p.name != "scene_topdown.png")

    def scan(d):
        with np.load(d / "lidar_scan.npz") as z:
            return {k: z[k] for k in z.files}

    # one seed: the same bytes
    assert (a / "groundtruth_tum.txt").read_bytes() == (b / "groundtruth_tum.txt").read_bytes()
    for name in images:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    sa, sb, sc_ = scan(a), scan(b), scan(c)
    assert sa.keys() == sb.keys() == {"points", "times_s", "ring", "intensity", "stamp"}
    for k in sa:
        np.testing.assert_array_equal(sa[k], sb[k])
    # another seed: the same world and motion, different sensor noise
    assert (a / "groundtruth_tum.txt").read_bytes() == (c / "groundtruth_tum.txt").read_bytes()
    assert not np.array_equal(sa["points"], sc_["points"])
    rgb = [n for n in images if n.startswith("rgb_")][0]
    depth = [n for n in images if n.startswith("depth_")][0]
    assert (a / rgb).read_bytes() != (c / rgb).read_bytes()
    assert (a / depth).read_bytes() != (c / depth).read_bytes()


def _random_steps(n: int, seed: int = 0):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    stamps = np.arange(n) / 240.0
    xyz = np.cumsum(rng.normal(0, 1e-3, (n, 3)), axis=0)
    quat = Rotation.from_rotvec(np.cumsum(rng.normal(0, 1e-3, (n, 3)), axis=0)).as_quat()
    return stamps, xyz, quat


def test_the_ground_truth_record_keeps_every_pose_as_it_grows_and_spills_to_disk():
    from sim.episode import GroundTruth
    from stack.transforms import from_xyz_quat

    stamps, xyz, quat = _random_steps(5000)
    gt = GroundTruth(memory_rows=1024)
    for t, x, q in zip(stamps, xyz, quat):
        gt.add(t, tuple(x), tuple(q))
    assert len(gt) == 5000 and gt._n_buf <= 1024  # the rest went to the temporary file
    assert np.array_equal(gt.stamps, stamps)
    full = np.array([from_xyz_quat(tuple(x), tuple(q)) for x, q in zip(xyz, quat)])
    assert np.array_equal(gt.T_world_base, full)  # the matrices the episode computed, bit for bit
    s, P = gt.window(1000, 1100)
    assert np.array_equal(s, stamps[1000:1100]) and np.array_equal(P, full[1000:1100])
    s, P = gt.window(len(gt) - 30)
    assert np.array_equal(P, full[-30:])


def test_ground_truth_lookups_are_bit_for_bit_those_of_the_whole_trajectory():
    from sim.episode import GroundTruth
    from stack.transforms import from_xyz_quat, interpolate_trajectory

    stamps, xyz, quat = _random_steps(6000, seed=1)
    gt = GroundTruth(memory_rows=2048)
    for t, x, q in zip(stamps, xyz, quat):
        gt.add(t, x, q)
    full = np.array([from_xyz_quat(x, q) for x, q in zip(xyz, quat)])
    rng = np.random.default_rng(2)
    tq = np.concatenate([rng.uniform(-1.0, stamps[-1] + 1.0, 500), stamps[rng.integers(0, len(stamps), 200)],
                         [stamps[0], stamps[-1], stamps[1023], stamps[1024], stamps[2048], -3.0, 99.0]])
    assert np.array_equal(gt.T_world_base_at(tq), interpolate_trajectory(stamps, full, tq))
    for t in tq[::25]:
        assert np.array_equal(gt.T_world_base_at(float(t)), interpolate_trajectory(stamps, full, float(t)))
    one = GroundTruth(memory_rows=1024)
    one.add(0.5, xyz[0], quat[0])
    assert np.array_equal(one.T_world_base_at(3.0), full[0])
