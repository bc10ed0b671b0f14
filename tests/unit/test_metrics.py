"""Metrics against hand-computed cases."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stack import metrics
from stack.transforms import from_xyz_rpy, make_T


def _poses(xyz, yaws_deg=None):
    xyz = np.asarray(xyz, dtype=float)
    yaws = np.zeros(len(xyz)) if yaws_deg is None else np.radians(yaws_deg)
    return np.array([from_xyz_rpy(p, [0, 0, y]) for p, y in zip(xyz, yaws)])


def test_ate_rmse_with_identity_alignment():
    est = _poses([[0, 0, 0], [1, 0, 0]])
    gt = _poses([[0, 0, 0], [1, 1, 0]])
    assert metrics.ate_errors(est, gt) == pytest.approx([0.0, 1.0])
    assert metrics.ate_rmse(est, gt) == pytest.approx(math.sqrt(0.5))


def test_ate_rmse_with_given_alignment():
    gt = _poses([[1, 0, 0], [2, 0, 0]])
    est = _poses([[0, 0, 0], [1, 0, 0]])
    assert metrics.ate_rmse(est, gt) == pytest.approx(1.0)
    assert metrics.ate_rmse(est, gt, T_align=make_T(t=[1, 0, 0])) == pytest.approx(0.0)


def test_umeyama_recovers_a_rigid_motion():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = Rotation.from_euler("zyx", [30, -10, 5], degrees=True).as_matrix()
    dst = src @ R.T + [1.0, -2.0, 0.5]
    T, s = metrics.umeyama_alignment(src, dst)
    assert s == 1.0
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1.0, -2.0, 0.5], atol=1e-12)
    _, s2 = metrics.umeyama_alignment(src, 2.0 * dst, with_scale=True)
    assert s2 == pytest.approx(2.0)


def test_ate_umeyama_of_a_scaled_square_is_the_scale_error():
    # a square of radius 1 and the same square 10 % larger: by symmetry the best rigid alignment is the
    # identity, and every corner is 0.1 m off.
    gt = _poses([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]])
    est = _poses(1.1 * np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]]))
    assert metrics.ate_rmse_umeyama(est, gt) == pytest.approx(0.1)
    # a rigidly moved copy aligns perfectly, while the unaligned error is large
    moved = np.array([from_xyz_rpy([3, 4, 0], [0, 0, 0.7]) @ T for T in gt])
    assert metrics.ate_rmse_umeyama(moved, gt) == pytest.approx(0.0, abs=1e-12)
    assert metrics.ate_rmse(moved, gt) > 3.0


def test_rpe_of_a_one_percent_scale_error_is_one_percent():
    x = np.arange(31) * 0.1  # 3 m straight line
    gt = _poses(np.c_[x, np.zeros_like(x), np.zeros_like(x)])
    est = _poses(np.c_[1.01 * x, np.zeros_like(x), np.zeros_like(x)])
    r = metrics.rpe(est, gt, delta_m=1.0)
    assert r.trans_pct == pytest.approx(1.0, rel=1e-9)
    assert r.rot_deg_per_m == pytest.approx(0.0, abs=1e-9)
    assert r.pairs == 21  # starts at 0.0 .. 2.0 m reach a pose 1 m further
    assert metrics.rpe(gt, gt).trans_pct == pytest.approx(0.0, abs=1e-12)


def test_rpe_rotation_drift_of_one_degree_per_metre():
    x = np.arange(21) * 0.1
    gt = _poses(np.c_[x, np.zeros_like(x), np.zeros_like(x)])
    est = _poses(np.c_[x, np.zeros_like(x), np.zeros_like(x)], yaws_deg=x)  # heading drifts 1 deg per metre
    r = metrics.rpe(est, gt, delta_m=0.5)
    assert r.rot_deg_per_m == pytest.approx(1.0, rel=1e-6)


def test_rpe_counts_a_standing_start_once():
    x = np.concatenate([np.zeros(50), np.arange(1, 21) * 0.1])  # 50 poses standing, then 2 m
    gt = _poses(np.c_[x, np.zeros_like(x), np.zeros_like(x)])
    est = gt.copy()
    est[60:, 0, 3] += 0.01  # a 1 cm jump in the estimate between 1.0 and 1.1 m
    r = metrics.rpe(est, gt, delta_m=1.0)
    assert r.pairs == 11  # starts: the standing pose (once), then the poses at 0.1 .. 1.0 m
    # (standing -> 1.0 m) misses the jump; (0.1 -> 1.1 m) .. (1.0 -> 2.0 m) each see 1 cm over 1 m
    assert r.trans_pct == pytest.approx(100 * 10 * 0.01 / 11)


def test_rpe_is_nan_when_the_path_is_shorter_than_delta():
    gt = _poses([[0, 0, 0], [0.3, 0, 0]])
    r = metrics.rpe(gt, gt, delta_m=1.0)
    assert r.pairs == 0 and math.isnan(r.trans_pct)


def test_tum_round_trip_and_format(tmp_path):
    poses = np.array([np.eye(4), from_xyz_rpy([1.0, -2.0, 0.25], [0.1, -0.2, 2.5])])
    path = metrics.write_tum(tmp_path / "traj.txt", [1.5, 1.6], poses)
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    assert lines[0].split() == ["1.500000000"] + ["0.000000000"] * 6 + ["1.000000000"]
    stamps, back = metrics.read_tum(path)
    np.testing.assert_allclose(stamps, [1.5, 1.6])
    np.testing.assert_allclose(back, poses, atol=1e-8)
    assert not list(tmp_path.glob("*.tmp"))


def test_tum_errors_name_file_and_line(tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text("# header\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n")
    with pytest.raises(metrics.TrajectoryFileError, match=r"bad\.txt:3: expected 8 numbers"):
        metrics.read_tum(bad)
    bad.write_text("0 0 0 0 0 0 0 2\n")
    with pytest.raises(metrics.TrajectoryFileError, match=r"bad\.txt:1: .*unit quaternion"):
        metrics.read_tum(bad)
    with pytest.raises(metrics.TrajectoryFileError, match="missing.txt"):
        metrics.read_tum(tmp_path / "missing.txt")


def test_cuboid_keypoints_follow_dope_order():
    k = metrics.cuboid_points([0.2, 0.4, 0.6])
    assert k.shape == (9, 3)
    np.testing.assert_allclose(k[0], [0.1, 0.2, 0.3])  # FrontTopRight: +x right, +y top, +z front
    np.testing.assert_allclose(k[6], [-0.1, -0.2, -0.3])  # RearBottomLeft
    np.testing.assert_allclose(k[8], [0, 0, 0])


def test_cuboid_surface_points_lie_on_the_surface():
    d = np.array([0.2, 0.4, 0.6])
    p = metrics.cuboid_points(d, kind="surface", n=500, seed=3)
    rel = np.abs(p) / (d / 2)
    assert np.all(rel <= 1 + 1e-12)
    np.testing.assert_allclose(rel.max(axis=1), 1.0)
    np.testing.assert_array_equal(p, metrics.cuboid_points(d, kind="surface", n=500, seed=3))


def test_add_and_adds():
    dims = [0.3, 0.1, 0.4]
    pts = metrics.cuboid_points(dims)
    T_gt = from_xyz_rpy([0.1, 0.2, 1.0], [0.3, 0.2, 0.1])
    assert metrics.add_error(T_gt @ make_T(t=[0.01, 0, 0]), T_gt, pts) == pytest.approx(0.01)
    # half a turn about the object's y axis maps the corner set onto itself: ADD-S 0, ADD does not
    flipped = T_gt @ make_T(Rotation.from_euler("y", 180, degrees=True).as_matrix())
    assert metrics.adds_error(flipped, T_gt, pts) == pytest.approx(0.0, abs=1e-12)
    assert metrics.add_error(flipped, T_gt, pts) == pytest.approx(8 / 9 * math.hypot(0.3, 0.4))


def test_paper_distance_and_accuracy():
    truth, det = [0.6, 0.0, 0.8], [0.0, 0.5, 0.9]
    assert metrics.paper_distance_xz(truth, det) == pytest.approx(math.sqrt(0.37))  # y ignored
    assert metrics.paper_accuracy(truth, det) == pytest.approx(0.9)  # |T| = 1.0, |D| = 0.9
    assert metrics.paper_label_distance([0, 0, 0], [0.1, 0.2, 0.2]) == pytest.approx(0.3)


def test_false_positive_is_any_axis_beyond_five_cm():
    assert not metrics.is_false_positive([0, 0, 0], [0.049, -0.049, 0.049])
    assert metrics.is_false_positive([0, 0, 0], [0.0, 0.0, -0.051])


def test_precision_recall_f():
    r = metrics.precision_recall_f(total_predictions=100, false_positives=10, total_instances=200)
    assert (r.correct, r.precision, r.recall) == (90, pytest.approx(0.9), pytest.approx(0.45))
    assert r.f_score == pytest.approx(0.6)
    assert r.f_score == pytest.approx(2 * r.precision * r.recall / (r.precision + r.recall))
    assert math.isnan(metrics.precision_recall_f(0, 0, 5).precision)
    with pytest.raises(ValueError):
        metrics.precision_recall_f(5, 6, 10)
