"""Depth refinement of DOPE poses against hand-built depth images (numpy ray casting, no renderer)."""
import numpy as np
import pytest

from stack.dope.depth_refine import _ray_box_depth, refine_translation

K = np.array([[615.0, 0, 319.5], [0, 615.0, 239.5], [0, 0, 1]])
DIMS = np.array([0.10, 0.14, 0.035])


def _pose(x=0.05, y=0.02, z=0.9, yaw=0.4):
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    T[:3, 3] = [x, y, z]
    return T


def _depth_image(T, wall=2.0):
    vv, uu = np.mgrid[0:480, 0:640]
    z = _ray_box_depth(T, DIMS, K, uu.ravel().astype(float), vv.ravel().astype(float)).reshape(480, 640)
    return np.where(np.isfinite(z), z, wall)


def _off_range(T, dz):
    T2 = T.copy()
    T2[:3, 3] *= (T[2, 3] + dz) / T[2, 3]
    return T2


@pytest.mark.parametrize("dz", [-0.12, -0.03, 0.04, 0.15])
def test_range_error_is_removed_and_image_position_kept(dz):
    T = _pose()
    fit = refine_translation(_off_range(T, dz), DIMS, K, _depth_image(T))
    assert fit.ok is True and fit.inlier_frac > 0.9
    assert np.linalg.norm(fit.T_cam_obj[:3, 3] - T[:3, 3]) < 0.005
    assert fit.shift_m == pytest.approx(-np.linalg.norm(_off_range(T, dz)[:3, 3]) + np.linalg.norm(T[:3, 3]), abs=0.005)


def test_noise_holes_and_a_partial_occluder_are_tolerated():
    T = _pose(z=1.2)
    rng = np.random.default_rng(0)
    depth = _depth_image(T) + rng.normal(0, 0.01, (480, 640))
    depth[rng.random((480, 640)) < 0.2] = 0.0  # holes
    depth[:, :322] = np.minimum(depth[:, :322], 0.6)  # a pole in front of the left part of the object
    fit = refine_translation(_off_range(T, 0.1), DIMS, K, depth)
    assert fit.ok
    assert abs(fit.T_cam_obj[2, 3] - T[2, 3]) < 0.01


def test_no_depth_or_inconsistent_depth_leaves_the_pose():
    T = _off_range(_pose(), 0.05)
    fit = refine_translation(T, DIMS, K, np.zeros((480, 640)))
    assert not fit.ok and fit.n_pixels == 0 and np.array_equal(fit.T_cam_obj, T)
    rng = np.random.default_rng(1)
    fit = refine_translation(T, DIMS, K, rng.uniform(0.3, 3.0, (480, 640)))  # no surface there
    assert not fit.ok and np.array_equal(fit.T_cam_obj, T)
    with pytest.raises(ValueError, match="2D"):
        refine_translation(T, DIMS, K, np.zeros((480, 640, 3)))
