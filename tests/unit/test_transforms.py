"""stack.transforms.from_xyz_quat, to_xyz_quat and the robot's per-step limits: the same bits as the
SciPy and NumPy calls they stand in for, on any input."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim.robot import _clip
from stack.transforms import from_xyz_quat, make_T, to_xyz_quat


def scipy_T(xyz, quat):
    return make_T(Rotation.from_quat(np.asarray(quat, dtype=float)).as_matrix(), xyz)


def test_from_xyz_quat_gives_scipys_bits_for_any_quaternion():
    rng = np.random.default_rng(5)
    for scale in (1e-150, 1e-6, 1e-2, 1.0, 30.0, 1e150):
        for q, t in zip(rng.standard_normal((2000, 4)) * scale, rng.standard_normal((2000, 3)) * 20):
            got = from_xyz_quat(tuple(t), tuple(q))
            want = scipy_T(t, q)
            assert got.dtype == want.dtype and got.shape == (4, 4)
            assert got.tobytes() == want.tobytes(), (q, t)


def test_from_xyz_quat_gives_scipys_bits_for_a_ground_robots_headings():
    for th in np.linspace(-7.0, 7.0, 2001):
        q = (0.0, 0.0, math.sin(th / 2), math.cos(th / 2))
        assert from_xyz_quat([1.5, -2.0, 0.06], q).tobytes() == scipy_T([1.5, -2.0, 0.06], q).tobytes()


def test_from_xyz_quat_takes_numpy_inputs_and_returns_a_new_array():
    q = np.array([0.1, -0.2, 0.3, 0.9])
    t = np.array([1.0, 2.0, 3.0])
    a = from_xyz_quat(t, q)
    b = from_xyz_quat(t, q)
    a[0, 0] = 7.0
    assert b[0, 0] != 7.0
    assert b.tobytes() == scipy_T(t, q).tobytes()


@pytest.mark.parametrize("quat", [(0.0, 0.0, 0.0, 0.0), (1.0, 2.0, 3.0), [[0.0, 0.0, 0.0, 1.0]] * 2])
def test_from_xyz_quat_raises_scipys_error_for_a_quaternion_it_cannot_use(quat):
    with pytest.raises(ValueError) as ours:
        from_xyz_quat([0.0, 0.0, 0.0], quat)
    with pytest.raises(ValueError) as theirs:
        scipy_T([0.0, 0.0, 0.0], quat)
    assert str(ours.value) == str(theirs.value)


def test_from_xyz_quat_treats_nan_and_inf_as_scipy_does():
    for quat in [(math.nan, 0.0, 0.0, 1.0), (math.inf, 0.0, 0.0, 1.0)]:
        try:
            want = scipy_T([0.0, 0.0, 0.0], quat)
        except ValueError as exc:
            with pytest.raises(ValueError, match=str(exc)):
                from_xyz_quat([0.0, 0.0, 0.0], quat)
        else:
            np.testing.assert_array_equal(from_xyz_quat([0.0, 0.0, 0.0], quat), want)


def scipy_xyz_quat(T):
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat()


def assert_same_xyz_quat(T):
    try:
        want = scipy_xyz_quat(T)
    except ValueError as exc:
        with pytest.raises(ValueError) as ours:
            to_xyz_quat(T)
        assert str(ours.value) == str(exc)
        return
    got = to_xyz_quat(T)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert g.tobytes() == w.tobytes(), T


def test_to_xyz_quat_gives_scipys_bits_for_rotations_and_their_products():
    rng = np.random.default_rng(11)
    R = Rotation.random(2000, random_state=12).as_matrix()
    for i in range(2000):
        T = make_T(R[i], rng.standard_normal(3) * 10)
        assert_same_xyz_quat(T)
        # chained transforms, as the map fusion makes them: orthogonal to about 1e-15
        assert_same_xyz_quat(T @ make_T(R[(7 * i) % 2000], [1.0, -2.0, 0.5]) @ make_T(R[(11 * i) % 2000]))
    # each branch of the largest-of-diagonal-and-trace choice, and its ties (half turns, the identity)
    for angle in np.linspace(-7.0, 7.0, 701):
        for axis in np.eye(3):
            assert_same_xyz_quat(make_T(Rotation.from_rotvec(axis * angle).as_matrix(), [0.3, 0.0, -1.0]))
    for d in ([1.0, 1.0, 1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, -1.0, -1.0]):
        assert_same_xyz_quat(make_T(np.diag(d)))


def test_to_xyz_quat_gives_scipys_bits_where_scipy_orthogonalises_first():
    # SciPy takes a rotation off by more than 1e-12 to its nearest orthogonal matrix first: around
    # that tolerance both ways must agree, whichever path each input takes
    rng = np.random.default_rng(13)
    R = Rotation.random(300, random_state=14).as_matrix()
    for eps in (1e-15, 1e-14, 3e-14, 1e-13, 3e-13, 1e-12, 1e-9, 1e-3):
        for i in range(300):
            assert_same_xyz_quat(make_T(R[i] + rng.standard_normal((3, 3)) * eps, [1.0, 2.0, 3.0]))


@pytest.mark.filterwarnings("ignore:invalid value encountered in det")
@pytest.mark.parametrize("R", [np.diag([1.0, 1.0, -1.0]), np.zeros((3, 3)), np.full((3, 3), np.nan)])
def test_to_xyz_quat_leaves_reflections_and_nan_to_scipy(R):
    T = make_T()
    T[:3, :3] = R
    assert_same_xyz_quat(T)
    assert_same_xyz_quat(T.astype(np.float32))


def test_to_xyz_quat_returns_new_arrays():
    T = make_T(Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix(), [1.0, 2.0, 3.0])
    xyz, quat = to_xyz_quat(T)
    xyz[0] = 9.0
    assert T[0, 3] == 1.0 and quat.flags.writeable and quat.shape == (4,)


def test_robot_limits_clip_as_numpy_does():
    values = [-3.0, -1.0, -0.5, -0.0, 0.0, 0.25, 1.0, 2.5, math.inf, -math.inf, math.nan]
    for x in values:
        for limit in (0.5, 1.0, 2.0):
            got = _clip(x, limit)
            want = float(np.clip(x, -limit, limit))
            assert type(got) is float
            assert np.array_equal(got, want, equal_nan=True) and math.copysign(1, got) == math.copysign(1, want)
