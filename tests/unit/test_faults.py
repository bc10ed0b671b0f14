"""Sensor faults (``sim.faults``): parsing and validation, and each fault's effect on a hand-built
message stream (rates within tolerance for the seed, stamps as specified, images changed as said)."""
from __future__ import annotations

import numpy as np
import pytest

from sim.faults import FaultError, FaultInjector, Faults, parse_overrides
from stack.messages import CameraFrame, CameraInfo, LidarScan, WheelOdometry

INFO = CameraInfo.from_fov(64, 48, 50.0)


def stream(seconds: float = 20.0, yaw_rate: float = 0.0):
    """A 10 Hz LiDAR (points all round), 10 Hz camera and 20 Hz wheel odometry, in time order."""
    rng = np.random.default_rng(0)
    az = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    pts = np.column_stack([5 * np.cos(az), 5 * np.sin(az), np.zeros_like(az)]).astype(np.float32)
    img = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    img[:, ::8] = 255  # vertical stripes: blur along x shows
    out = []
    for k in range(int(seconds * 20)):
        t = 0.05 * k
        T = np.eye(4)
        T[0, 3] = 0.5 * t
        out.append(WheelOdometry(t, T, 0.5, 0.0))
        if k % 2 == 0:
            c, s = np.cos(yaw_rate * t), np.sin(yaw_rate * t)
            Tc = np.eye(4)
            Tc[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]  # turning about the optical y axis
            out.append(CameraFrame(t, INFO, img.copy(), np.full((48, 64), 2.0, np.float32), Tc))
        if k % 2 == 1 and k > 2:
            out.append(LidarScan(t - 0.1, pts.copy(), np.linspace(0, 0.1, len(pts))))
    return out


def run(faults: Faults, seed: int = 0, **kw):
    inj = FaultInjector(faults, seed)
    return inj, list(inj.apply(stream(**kw)))


def of(msgs, kind):
    return [m for m in msgs if isinstance(m, kind)]


def test_parse_and_validate():
    f = parse_overrides(["lidar_drop=0.2", "camera_latency=0.05"], Faults(camera_drop=0.1))
    assert (f.lidar_drop, f.camera_latency, f.camera_drop) == (0.2, 0.05, 0.1)
    assert f.active == {"lidar_drop": 0.2, "camera_drop": 0.1, "camera_latency": 0.05}
    for bad, says in [("lidar_drop=1.5", "lidar_drop"), ("nothing=1", "expected NAME=VALUE"),
                      ("camera_drop", "expected NAME=VALUE"), ("camera_drop=lots", "expected a number")]:
        with pytest.raises(FaultError, match=says):
            parse_overrides([bad])


def test_scenario_faults_table(tmp_path):
    from sim.scenario import ScenarioError, load_scenario

    text = open(load_scenario().source).read()
    p = tmp_path / "f.toml"
    p.write_text(text + "\n[faults]\nlidar_drop = 0.3\ncamera_latency = 0.05\n")
    sc = load_scenario(p)
    assert sc.faults.lidar_drop == 0.3 and sc.faults.camera_latency == 0.05
    p.write_text(text + "\n[faults]\ncamera_drop = 2\n")
    with pytest.raises(ScenarioError, match="faults.camera_drop"):
        load_scenario(p)


def test_no_faults_no_change():
    clean = stream()
    msgs = list(FaultInjector(Faults(), 0).apply(clean))
    assert len(msgs) == len(clean)
    assert all(a is b for a, b in zip(msgs, clean))


@pytest.mark.parametrize("rate", [0.2, 0.5])
def test_drop_rates_within_tolerance(rate):
    n_scans, n_imgs = len(of(stream(), LidarScan)), len(of(stream(), CameraFrame))
    inj, msgs = run(Faults(lidar_drop=rate, camera_drop=rate))
    kept_s, kept_i = len(of(msgs, LidarScan)) / n_scans, len(of(msgs, CameraFrame)) / n_imgs
    tol = 3 * np.sqrt(rate * (1 - rate) / n_scans)
    assert abs(kept_s - (1 - rate)) < tol and abs(kept_i - (1 - rate)) < tol
    assert inj.counts["scans_dropped"] == n_scans - len(of(msgs, LidarScan))
    # the same seed drops the same messages; another seed others
    assert [m.stamp for m in run(Faults(lidar_drop=rate), seed=0)[1]] == \
        [m.stamp for m in run(Faults(lidar_drop=rate), seed=0)[1]]
    assert [m.stamp for m in run(Faults(lidar_drop=rate), seed=0)[1]] != \
        [m.stamp for m in run(Faults(lidar_drop=rate), seed=1)[1]]


def test_partial_sweeps_lose_a_wedge():
    inj, msgs = run(Faults(partial_sweep=1.0))
    scans = of(msgs, LidarScan)
    kept = [len(s.points) / 720 for s in scans]
    assert all(0.25 <= k <= 0.75 for k in kept) and len(scans) == inj.counts["scans_partial"]
    az = np.sort(np.arctan2(scans[0].points[:, 1], scans[0].points[:, 0]))
    gaps = np.diff(np.concatenate([az, az[:1] + 2 * np.pi]))
    assert gaps.max() > 0.3 * 2 * np.pi  # one contiguous wedge is missing
    assert len(scans[0].times_s) == len(scans[0].points)


def test_latency_keeps_true_stamps_and_arrives_late():
    _, msgs = run(Faults(camera_latency=0.07))
    clean_stamps = [m.stamp for m in of(stream(), CameraFrame)]
    assert [m.stamp for m in of(msgs, CameraFrame)] == clean_stamps  # true stamps
    # each image comes after the wheel messages stamped before its arrival (stamp + 0.07 s), before later ones
    for i, m in enumerate(msgs):
        if isinstance(m, CameraFrame):
            wheel_before = [x.stamp for x in msgs[:i] if isinstance(x, WheelOdometry)]
            wheel_after = [x.stamp for x in msgs[i + 1:] if isinstance(x, WheelOdometry)]
            assert all(s < m.stamp + 0.07 + 1e-9 for s in wheel_before)
            assert all(s > m.stamp + 0.07 - 1e-9 for s in wheel_after)
            assert max(wheel_before) > m.stamp  # it did not come on time


def test_late_stamps_and_clock_offset_are_wrong_stamps():
    clean = [m.stamp for m in of(stream(), CameraFrame)]
    _, late = run(Faults(camera_late_stamp=0.1))
    assert np.allclose([m.stamp for m in of(late, CameraFrame)], np.array(clean) + 0.1)
    _, off = run(Faults(camera_clock_offset=-0.03))
    assert np.allclose([m.stamp for m in of(off, CameraFrame)], np.array(clean) - 0.03)
    # LiDAR stamps are untouched; the ground truth in the frame stays the true pose at capture
    assert [m.stamp for m in of(off, LidarScan)] == [m.stamp for m in of(stream(), LidarScan)]


def test_depth_holes_fraction():
    _, msgs = run(Faults(depth_holes=0.2))
    frac = np.mean([np.mean(m.depth_m == 0) for m in of(msgs, CameraFrame)])
    assert abs(frac - 0.2) < 0.02
    assert not np.array_equal(of(msgs, CameraFrame)[0].depth_m == 0, of(msgs, CameraFrame)[1].depth_m == 0)


def test_exposure_and_flicker():
    clean = of(stream(), CameraFrame)[0].rgb.astype(float).mean()
    _, dark = run(Faults(exposure=0.5))
    assert abs(of(dark, CameraFrame)[0].rgb.astype(float).mean() - 0.5 * clean) < 2
    _, flick = run(Faults(flicker=0.5))
    means = np.array([m.rgb.astype(float).mean() for m in of(flick, CameraFrame)])
    assert means.std() > 0.1 * clean and means.min() >= 0.5 * clean - 2


def test_motion_blur_smears_along_the_motion():
    _, still = run(Faults(motion_blur=0.03))
    assert np.array_equal(of(still, CameraFrame)[3].rgb, of(stream(), CameraFrame)[3].rgb)  # no motion, no blur
    _, turning = run(Faults(motion_blur=0.03), yaw_rate=1.0)  # 1 rad/s: 50 px/s * fx ... ~1.5 px per ms
    a = of(turning, CameraFrame)[3].rgb.astype(float)
    b = of(stream(yaw_rate=1.0), CameraFrame)[3].rgb.astype(float)
    assert np.abs(np.diff(a, axis=1)).mean() < 0.7 * np.abs(np.diff(b, axis=1)).mean()  # smoother along x


def test_wheel_slip_over_reports_distance():
    _, msgs = run(Faults(wheel_slip=0.2))
    wheel = of(msgs, WheelOdometry)
    true_end = of(stream(), WheelOdometry)[-1].T_odom_base[0, 3]
    ratio = wheel[-1].T_odom_base[0, 3] / true_end
    assert 1.05 < ratio < 1.15  # on average 1 + 0.2 / 2


def test_experiment_sweep_option():
    from pydantic import ValidationError

    from testbed.experiments.faults import SWEEP, parse_faults_option

    assert parse_faults_option("lidar_drop=0,0.2;camera_latency=0,0.05") == \
        {"lidar_drop": (0.0, 0.2), "camera_latency": (0.0, 0.05)}
    assert set(SWEEP) == set(Faults.model_fields)  # every fault has a default sweep
    with pytest.raises(ValueError, match="expected NAME=RATE"):
        parse_faults_option("nothing=1")
    with pytest.raises(ValidationError):
        parse_faults_option("camera_drop=0,3")
