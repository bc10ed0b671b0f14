"""Monocular pose (the topological-map paper, section 2.2): the eight-point essential matrix, the translation's
length from one known point, ORPE, Grunert's P3P and TRPE on synthetic correspondences."""
import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stack.topomap.mono_pose import (MonoConfig, bearings, decompose_essential, eight_point, grunert, grunert_p3p, normalise,
                             orpe, project, refine_pose_lm, scale_from_point, triangulate, trpe)

K = np.array([[610.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]])


def scene(seed=0, n=200, planar=False):
    rng = np.random.default_rng(seed)
    X = rng.uniform([-2, -1, 2], [2, 1, 6], (n, 3))
    if planar:
        X[:, 2] = 4.0 + 0.001 * rng.standard_normal(n)
    R = Rotation.from_rotvec([0.02, 0.12, -0.01]).as_matrix()
    t = np.array([0.08, 0.01, 0.25])
    uv1, _ = project(K, np.eye(3), np.zeros(3), X)
    uv2, _ = project(K, R, t, X)
    return X, R, t, uv1, uv2, rng


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def test_eight_point_recovers_the_essential_matrix_and_its_decomposition_contains_the_motion():
    X, R, t, uv1, uv2, _ = scene()
    E = eight_point(normalise(uv1[:8], K), normalise(uv2[:8], K))
    E_true = skew(t) @ R
    E_true /= np.linalg.norm(E_true)
    assert min(np.abs(E - E_true).max(), np.abs(E + E_true).max()) < 1e-8
    Rs, ts = decompose_essential(E)
    hits = [k for k in range(4) if np.allclose(Rs[k], R, atol=1e-8) and np.allclose(ts[k], t / np.linalg.norm(t), atol=1e-8)]
    assert len(hits) == 1
    # batched: a stack of samples gives a stack of matrices
    Eb = eight_point(np.stack([normalise(uv1[:8], K), normalise(uv1[8:16], K)]),
                     np.stack([normalise(uv2[:8], K), normalise(uv2[8:16], K)]))
    assert Eb.shape == (2, 3, 3)


def test_the_translation_length_from_one_known_point():
    X, R, t, _, uv2, _ = scene()
    x2 = np.r_[normalise(uv2[:1], K)[0], 1.0]
    s = scale_from_point(R, t / np.linalg.norm(t), X[0], x2)
    assert s == pytest.approx(np.linalg.norm(t), rel=1e-9)


@pytest.mark.parametrize("outliers", [0.0, 0.3])
def test_orpe_recovers_pose_with_noise_and_outliers(outliers):
    X, R, t, uv1, uv2, rng = scene(1)
    uv = uv2 + rng.normal(0, 0.5, uv2.shape)
    bad = rng.random(len(uv)) < outliers
    uv[bad] += rng.uniform(-40, 40, (bad.sum(), 2))
    est = orpe(K, X, uv1, uv, np.random.default_rng(0))
    assert est is not None
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(est.R.T @ R).as_rotvec())) < 0.2
    assert np.linalg.norm(est.t - t) < 0.01
    assert est.inliers[bad].mean() < 0.1 if bad.any() else True
    assert est.inliers[~bad].mean() > 0.9


def test_grunert_p3p_matches_opencv_and_the_truth():
    X, R, t, _, uv2, _ = scene(2)
    sols = grunert_p3p(bearings(uv2[:3], K), X[:3])
    assert 1 <= len(sols) <= 4
    assert any(np.allclose(Rs, R, atol=1e-7) and np.allclose(ts, t, atol=1e-7) for Rs, ts in sols)
    n, rvecs, tvecs = cv2.solveP3P(X[:3].astype(np.float64), uv2[:3].astype(np.float64), K, None, cv2.SOLVEPNP_P3P)
    cv_sols = [(cv2.Rodrigues(r)[0], tv.ravel()) for r, tv in zip(rvecs, tvecs)]
    for Rc, tc in cv_sols:  # every OpenCV solution is one of ours
        assert any(np.allclose(Rs, Rc, atol=1e-6) and np.allclose(ts, tc, atol=1e-6) for Rs, ts in sols)


def test_grunert_ransac_and_lm_refinement():
    X, R, t, _, uv2, rng = scene(3)
    uv = uv2 + rng.normal(0, 0.5, uv2.shape)
    uv[:40] += 30.0
    est = grunert(K, X, uv, np.random.default_rng(1))
    assert est is not None and np.linalg.norm(est.t - t) < 0.01
    R2, t2 = refine_pose_lm(K, R @ Rotation.from_rotvec([0.01, 0, 0]).as_matrix(), t + 0.02, X[40:], uv[40:])
    assert np.linalg.norm(t2 - t) < 0.005


def test_trpe_works_on_a_good_configuration_and_orpe_survives_the_degenerate_one():
    X, R, t, uv1, uv2, rng = scene(4)
    uv = uv2 + rng.normal(0, 0.3, uv2.shape)
    est = trpe(K, X, uv1, uv, uv1, uv, np.random.default_rng(0))
    assert est is not None and np.linalg.norm(est.t - t) < 0.01
    # no translation and a planar scene: the essential matrix is undetermined (any [t]x R fits);
    # ORPE still finds the pose, because its hypotheses are judged by reprojecting the known points
    Xp, _, _, uv1p, _, rng = scene(5, planar=True)
    R0 = Rotation.from_rotvec([0.0, 0.05, 0.0]).as_matrix()
    uv2p, _ = project(K, R0, np.zeros(3), Xp)
    uv2p += rng.normal(0, 0.3, uv2p.shape)
    cfg = MonoConfig()
    ok_orpe = 0
    for s in range(10):
        e1 = orpe(K, Xp, uv1p, uv2p, np.random.default_rng(s), cfg)
        ok_orpe += e1 is not None and np.linalg.norm(e1.t) < 0.02 and np.allclose(e1.R, R0, atol=2e-3)
        assert e1 is None or e1.ransac_inliers >= cfg.min_inliers
    assert ok_orpe == 10


def test_triangulation_drops_points_behind_or_without_parallax():
    X, R, t, uv1, uv2, _ = scene(6)
    T2 = np.eye(4)
    T2[:3, :3], T2[:3, 3] = R, t
    Xt, ok = triangulate(K, np.eye(4), T2, uv1, uv2, min_parallax_deg=0.5)
    assert ok.mean() > 0.7
    assert np.abs(Xt[ok] - X[ok]).max() < 1e-6
    Xz, okz = triangulate(K, np.eye(4), np.eye(4), uv1, uv1)
    assert not okz.any()


def test_pose_figures_are_written(tmp_path):
    from testbed.topomap.pose_eval import plot_scenario

    t = np.linspace(0, 2, 20)
    xyz = np.stack([t, 0.1 * t, 0.3 + 0 * t], axis=1)
    curve = {"path_m": t, "rot_deg": 0.5 * t, "trans_m": 0.05 * t, "gt_xyz": xyz, "est_xyz": xyz + 0.02}
    plot_scenario({"scenario": "s", "methods": {"orpe": {"_curve": curve}, "trpe": {}}}, tmp_path)
    for f in ("fig15_rotation_s.png", "fig16_translation_s.png", "fig17_trajectory_s.png"):
        assert (tmp_path / f).stat().st_size > 1000
