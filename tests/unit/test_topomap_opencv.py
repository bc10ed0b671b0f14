"""The monocular pose's OpenCV parts against the hand-written code they replaced (kept here as the
reference): the Levenberg-Marquardt refinement (``cv2.solvePnPRefineLM`` vs scipy's LM), and the
essential matrix in RANSAC with its pose (``cv2.findEssentialMat`` + ``cv2.recoverPose`` vs our
eight-point RANSAC on Sampson error with cheirality), on noisy correspondences with outliers.
Tolerances: the refined pose within 1e-6 rad / 1e-6 m of the reference's (the same minimum); the
essential pose, over 30 scenes, no worse than the reference's (the test says by how much)."""
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from stack.topomap.mono_pose import (MonoConfig, _needed_iterations, _rotmat, _rotvec, _rt_to_T, _samples,
                                     decompose_essential, eight_point, essential_ransac, normalise,
                                     pose_from_essential, project, refine_pose_lm, triangulate, trpe)

K = np.array([[610.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]])


def scene(seed: int, n: int = 200, noise_px: float = 0.5, outliers: float = 0.3):
    rng = np.random.default_rng(seed)
    X = rng.uniform([-2, -1, 2], [2, 1, 6], (n, 3))
    R = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
    t = np.array([0.3, 0.02, 0.1]) + rng.normal(0, 0.03, 3)
    uv1, _ = project(K, np.eye(3), np.zeros(3), X)
    uv2, _ = project(K, R, t, X)
    uv1 = uv1 + rng.normal(0, noise_px, uv1.shape)
    uv2 = uv2 + rng.normal(0, noise_px, uv2.shape)
    bad = rng.random(n) < outliers
    uv2[bad] += rng.uniform(-40, 40, (int(bad.sum()), 2))
    return X, R, t, uv1, uv2, bad


def angle_deg(Ra, Rb) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(Ra.T @ Rb).as_rotvec())))


# --- the code replaced, as it was ---------------------------------------------------------------

def refine_reference(K, R, t, X, uv, iterations=20):
    def resid(p):
        px, _ = project(K, _rotmat(p[:3]), p[3:], X)
        return (px - uv).ravel()

    sol = least_squares(resid, np.r_[_rotvec(R), t], method="lm", max_nfev=iterations * 7)
    return _rotmat(sol.x[:3]), sol.x[3:].copy()


def sampson_px(E, x1h, x2h, f):
    Ex1 = np.einsum("...ij,nj->...ni", E, x1h)
    Etx2 = np.einsum("...ji,nj->...ni", E, x2h)
    num = np.einsum("ni,...ni->...n", x2h, Ex1)
    den = Ex1[..., 0] ** 2 + Ex1[..., 1] ** 2 + Etx2[..., 0] ** 2 + Etx2[..., 1] ** 2
    return f * np.abs(num) / np.sqrt(np.maximum(den, 1e-18))


def essential_reference(K, uv1, uv2, rng, cfg=MonoConfig(), batch=32):
    n = len(uv1)
    x1, x2 = normalise(uv1, K), normalise(uv2, K)
    x1h, x2h = np.column_stack([x1, np.ones(n)]), np.column_stack([x2, np.ones(n)])
    f = 0.5 * (K[0, 0] + K[1, 1])
    best_count, best = -1, None
    needed, done = cfg.max_iterations, 0
    while done < min(needed, cfg.max_iterations) or done < cfg.min_iterations:
        idx = _samples(rng, n, 8, batch)
        E = eight_point(x1[idx], x2[idx])
        counts = (sampson_px(E, x1h, x2h, f) < cfg.inlier_px).sum(-1)
        b = int(np.argmax(counts))
        done += batch
        if counts[b] > best_count:
            best_count, best = int(counts[b]), E[b]
            needed = _needed_iterations(best_count / n, 8, cfg.confidence, cfg.max_iterations)
    inl = sampson_px(best, x1h, x2h, f) < cfg.inlier_px
    E2 = eight_point(x1[inl], x2[inl])
    inl2 = sampson_px(E2, x1h, x2h, f) < cfg.inlier_px
    if inl2.sum() >= inl.sum():
        best, inl = E2, inl2
    return best, inl


def pose_reference(K, E, uv1, uv2):
    R, t = decompose_essential(E)
    best, best_n = None, -1
    for k in range(4):
        _, ok = triangulate(K, np.eye(4), _rt_to_T(R[k], t[k]), uv1, uv2, 0.0, 1e9, 1e9)
        if int(ok.sum()) > best_n:
            best_n, best = int(ok.sum()), (R[k], t[k])
    return best[0], best[1], best_n


# --- the comparisons ----------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(5))
def test_lm_refinement_reaches_the_reference_minimum(seed):
    X, R, t, _, uv2, bad = scene(seed)
    X, uv = X[~bad], uv2[~bad]
    R0 = R @ Rotation.from_rotvec([0.01, -0.005, 0.004]).as_matrix()
    t0 = t + [0.02, -0.01, 0.03]
    Rr, tr = refine_reference(K, R0, t0, X, uv)
    Rn, tn = refine_pose_lm(K, R0, t0, X, uv)
    assert np.radians(angle_deg(Rr, Rn)) < 1e-6
    assert np.linalg.norm(tr - tn) < 1e-6
    assert np.linalg.norm(tn - t) < 0.005  # and near the truth (0.5 px noise)


def test_essential_pose_at_least_as_good_as_the_reference():
    """30 scenes (0.5 px noise, 30 % outliers): median rotation and translation-direction errors
    against the truth no worse than the reference's by 0.1 deg and 0.5 deg, the true matches kept and
    the outliers let in within 2 points of the reference's rates (measured: reference 0.30 deg,
    1.9 deg, 96 %, 8.3 %; OpenCV 0.07 deg, 0.45 deg, 100 %, 8.2 %)."""
    ref, new = [], []
    for seed in range(30):
        X, R, t, uv1, uv2, bad = scene(seed)
        t_dir = t / np.linalg.norm(t)
        for out, (fe, fp) in ((ref, (essential_reference, pose_reference)),
                              (new, (essential_ransac, pose_from_essential))):
            E, inl = fe(K, uv1, uv2, np.random.default_rng(seed))
            Rm, tm, _ = fp(K, E, uv1[inl], uv2[inl])
            out.append((angle_deg(R, Rm), np.degrees(np.arccos(np.clip(tm @ t_dir, -1, 1))),
                        inl[~bad].mean(), inl[bad].mean()))
    ref, new = np.array(ref), np.array(new)
    assert np.median(new[:, 0]) <= np.median(ref[:, 0]) + 0.1
    assert np.median(new[:, 1]) <= np.median(ref[:, 1]) + 0.5
    assert new[:, 2].mean() >= ref[:, 2].mean() - 0.02
    assert new[:, 3].mean() <= ref[:, 3].mean() + 0.02


def test_essential_ransac_is_seeded():
    _, _, _, uv1, uv2, _ = scene(7)
    a = essential_ransac(K, uv1, uv2, np.random.default_rng(3))
    b = essential_ransac(K, uv1, uv2, np.random.default_rng(3))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert essential_ransac(K, uv1[:7], uv2[:7], np.random.default_rng(0)) is None


def test_trpe_with_the_opencv_essential_matrix():
    X, R, t, uv1, uv2, bad = scene(8, outliers=0.2)
    est = trpe(K, X, uv1, uv2, uv1, uv2, np.random.default_rng(0))
    assert est is not None and np.linalg.norm(est.t - t) < 0.02 and angle_deg(R, est.R) < 0.2


def test_trpe_takes_its_own_essential_threshold(monkeypatch):
    """TRPE's essential matrix uses ``trpe_essential_px``; the initialisation's keeps ``inlier_px``."""
    import stack.topomap.mono_pose as mp

    seen = []
    real = mp.essential_ransac
    monkeypatch.setattr(mp, "essential_ransac", lambda *a: seen.append(a[5] if len(a) > 5 else None) or real(*a))
    X, R, t, uv1, uv2, bad = scene(8, outliers=0.2)
    trpe(K, X, uv1, uv2, uv1, uv2, np.random.default_rng(0), MonoConfig(trpe_essential_px=0.7))
    assert seen == [0.7]
    _, inl_1 = real(K, uv1, uv2, np.random.default_rng(0), MonoConfig(), 1.0)
    _, inl_2 = real(K, uv1, uv2, np.random.default_rng(0), MonoConfig())
    assert inl_1.sum() < inl_2.sum()  # the default threshold is inlier_px (2 px): more inliers than 1 px
