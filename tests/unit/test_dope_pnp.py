"""Inference geometry: PnP on perfect key points, affinity association, the detector on constructed maps."""
import numpy as np
import pytest

from stack.dope_fpr import associate, cuboid_points, find_peaks, refine_peak, solve_pose
from stack.dope.targets import make_targets, to_output_coords
from stack.transforms import make_T

K = np.array([[610.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]])
DIMS = np.array([0.192483, 0.072781, 0.071583])


def _project(T, pts):
    p = pts @ T[:3, :3].T + T[:3, 3]
    return np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], 1)


@pytest.mark.parametrize("xyz,rpy", [((0.1, -0.05, 0.8), (0.3, -0.5, 0.1)), ((-0.3, 0.1, 1.5), (2.0, 0.2, -0.4)),
                                     ((0.0, 0.0, 0.5), (0.0, 3.0, 0.0))])
def test_pnp_on_perfect_keypoints_recovers_the_pose_to_a_millimetre(xyz, rpy):
    from scipy.spatial.transform import Rotation

    T = make_T(Rotation.from_euler("xyz", rpy).as_matrix(), np.array(xyz))
    uv = _project(T, cuboid_points(DIMS))
    T_est, err = solve_pose(uv, DIMS, K)
    assert np.linalg.norm(T_est[:3, 3] - T[:3, 3]) < 1e-3
    assert np.degrees(np.arccos(np.clip((np.trace(T_est[:3, :3].T @ T[:3, :3]) - 1) / 2, -1, 1))) < 0.1
    assert err < 1e-3


def test_pnp_with_missing_keypoints_and_too_few():
    T = make_T(np.eye(3), np.array([0.0, 0.0, 1.0]))
    uv = _project(T, cuboid_points(DIMS))
    uv[[1, 6]] = np.nan
    T_est, _ = solve_pose(uv, DIMS, K)
    assert np.linalg.norm(T_est[:3, 3] - T[:3, 3]) < 1e-3
    uv[[0, 2, 3, 4]] = np.nan
    assert solve_pose(uv, DIMS, K) is None


def test_peaks_and_subcell_refinement():
    m = np.zeros((10, 12), np.float32)
    m[4, 5], m[4, 6] = 1.0, 1.0  # a peak between two cells
    m[8, 2] = 0.5
    peaks = find_peaks(m, 0.1)
    assert len(peaks) == 2 and peaks[0][2] == 1.0 and peaks[1][:2] == (8, 2)
    x, y = refine_peak(m, 4, 5)
    assert x == pytest.approx(5.5) and y == pytest.approx(4.0)


def test_association_separates_two_objects_of_one_class():
    kps = []
    for cx in (60.0, 200.0):
        corners = [(cx + 20, 40), (cx - 20, 40), (cx - 20, 120), (cx + 20, 120),
                   (cx + 28, 34), (cx - 12, 34), (cx - 12, 114), (cx + 28, 114)]
        kps.append(np.array(corners + [(cx + 4, 77)]))
    b, a = make_targets(np.stack(kps), np.array([0, 0]), 1, (20, 32), sigma=1.0, radius=1.5)
    objs = associate(b, a, peak_threshold=0.3)
    assert len(objs) == 2
    for obj in objs:
        centre_in = obj.points[8]
        truth = min(kps, key=lambda k: np.linalg.norm(to_output_coords(k[8]) - centre_in))
        assert np.all(np.isfinite(obj.points))
        assert np.max(np.linalg.norm(obj.points - to_output_coords(truth), axis=1)) < 0.35
