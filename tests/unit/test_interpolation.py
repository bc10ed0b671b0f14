"""One pose looked up on a trajectory: only its segment is interpolated, with the same bits as the
whole trajectory gives (so a lookup costs the same however long the run)."""
import numpy as np
from scipy.spatial.transform import Rotation

from stack.transforms import interpolate_trajectory


def test_scalar_lookup_equals_the_whole_trajectory_bit_for_bit():
    rng = np.random.default_rng(1)
    n = 200
    stamps = np.cumsum(rng.uniform(0.05, 0.15, n))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(n, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(n, 3)) * 10
    queries = np.concatenate([stamps, rng.uniform(stamps[0] - 1, stamps[-1] + 1, 500)])
    whole = interpolate_trajectory(stamps, poses, queries)  # the (M, 4, 4) path: every segment at once
    for t, expected in zip(queries, whole):
        assert np.array_equal(interpolate_trajectory(stamps, poses, float(t)), expected), t
    # the ends clamp; two poses and one pose still work
    assert np.array_equal(interpolate_trajectory(stamps, poses, stamps[0] - 5), whole[0])
    np.testing.assert_allclose(interpolate_trajectory(stamps[:2], poses[:2], stamps[0]), poses[0], atol=1e-12)
    assert np.array_equal(interpolate_trajectory(stamps[:1], poses[:1], 3.0), poses[0])
