"""Fusion: the camera -> base -> map chain, pose interpolation at the image time, and the paper's HTM."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stack.fusion import (PoseLookupError, chain, fuse, htm_theta, object_in_map, paper_htm, paper_theta,
                          trajectory_lookup)
from stack.messages import Detection
from stack.transforms import from_xyz_rpy, make_T

# Optical frame (x right, y down, z forward) in base_link (x forward, y left, z up).
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0],
                           [-1.0, 0.0, 0.0],
                           [0.0, -1.0, 0.0]])


def camera_mount(d=0.2, h=0.3, pitch=0.0):
    """A camera d m ahead of base_link and h m up, looking forward, pitched down by ``pitch``."""
    R_tilt = Rotation.from_euler("y", pitch).as_matrix()
    return make_T(R_tilt @ R_BASE_OPTICAL, (d, 0.0, h))


def robot(x, y, yaw, z=0.0):
    return from_xyz_rpy((x, y, z), (0.0, 0.0, yaw))


def at(x_cam, y_cam, z_cam):
    return make_T(None, (x_cam, y_cam, z_cam))


def test_object_straight_ahead_of_a_robot_at_the_origin():
    T_map_obj = chain(np.eye(4), camera_mount(0.2, 0.3), at(0.0, 0.0, 1.0))
    np.testing.assert_allclose(T_map_obj[:3, 3], [1.2, 0.0, 0.3], atol=1e-12)


def test_object_seen_by_a_robot_turned_left():
    # Robot at (1, 2) facing map +y; object 2 m ahead and 0.5 m to the camera's right, 0.1 m below it.
    # base: (0.2 + 2, -0.5, 0.3 - 0.1); turned +90 deg: (x, y) -> (-y, x); then + (1, 2).
    T_map_obj = chain(robot(1.0, 2.0, np.pi / 2), camera_mount(0.2, 0.3), at(0.5, 0.1, 2.0))
    np.testing.assert_allclose(T_map_obj[:3, 3], [1.5, 4.2, 0.2], atol=1e-12)


def test_object_orientation_is_carried_into_the_map():
    # An object whose frame equals the camera's: in the map its z (front) points along the robot's
    # heading, its x (right) to the robot's right and its y down.
    T_map_obj = chain(robot(0.0, 0.0, np.pi / 2), camera_mount(), np.eye(4))
    np.testing.assert_allclose(T_map_obj[:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)


def test_pitched_camera_sees_the_floor_closer():
    # Camera 0.3 m up, pitched down 30 deg: an object 0.6 m along the optical axis is on the floor,
    # 0.6 cos 30 deg ahead of the camera.
    T_map_obj = chain(np.eye(4), camera_mount(0.0, 0.3, pitch=np.radians(30)), at(0.0, 0.0, 0.6))
    np.testing.assert_allclose(T_map_obj[:3, 3], [0.6 * np.cos(np.radians(30)), 0.0, 0.0], atol=1e-12)


def test_robot_pose_is_interpolated_at_the_image_timestamp():
    stamps = np.array([0.0, 1.0])
    poses = np.stack([robot(0.0, 0.0, 0.0), robot(1.0, 0.0, np.pi / 2)])
    # At t = 0.5 the robot is at (0.5, 0) with yaw 45 deg; the object is 1.2 m along its heading.
    expected = [0.5 + 1.2 * np.cos(np.pi / 4), 1.2 * np.sin(np.pi / 4), 0.3]
    for poses_arg in [(stamps, poses), trajectory_lookup(stamps, poses)]:
        T_map_obj = object_in_map(at(0.0, 0.0, 1.0), 0.5, poses_arg, camera_mount(0.2, 0.3))
        np.testing.assert_allclose(T_map_obj[:3, 3], expected, atol=1e-12)


def test_the_two_poses_around_the_image_time_are_interpolated():
    lookup = trajectory_lookup([0.0, 1.0, 2.0, 3.0], np.stack([robot(x, 0.0, 0.0) for x in (0.0, 1.0, 3.0, 3.5)]))
    assert [lookup(t)[0, 3] for t in (0.0, 0.25, 1.0, 1.5, 2.9, 3.0)] == pytest.approx([0, 0.25, 1, 2, 3.45, 3.5])


def test_an_image_outside_the_trajectory_has_no_pose():
    lookup = trajectory_lookup([0.0, 0.1], np.stack([np.eye(4), np.eye(4)]))
    with pytest.raises(PoseLookupError, match="t=0.150000"):
        lookup(0.15)
    np.testing.assert_allclose(trajectory_lookup([0.0, 0.1], np.stack([np.eye(4)] * 2), tolerance_s=0.1)(0.15),
                               np.eye(4))


def test_fuse_turns_a_detection_into_a_map_observation():
    det = Detection(cls="Mustard", stamp=0.5, T_cam_obj=at(0.3, 0.0, 0.4), keypoints_px=np.full((9, 2), np.nan),
                    peak_scores=np.zeros(9), belief_sum=12.5, fpr_pass=False)
    obs = fuse(det, (np.array([0.0, 1.0]), np.stack([np.eye(4), robot(2.0, 0.0, 0.0)])), camera_mount(0.2, 0.3))
    assert (obs.cls, obs.stamp, obs.belief_sum, obs.fpr_pass) == ("Mustard", 0.5, 12.5, False)
    np.testing.assert_allclose(obs.xyz, [1.0 + 0.2 + 0.4, -0.3, 0.3], atol=1e-12)
    assert obs.range_m == pytest.approx(0.5)


# --- The paper's HTM (eq. 1-2) is the chain on flat ground with a yaw-only pose ------------------

def random_flat_cases(n=50, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        yield (rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0.0, 0.3),  # x, y; yaw; d
               rng.uniform(0.1, 0.5), rng.uniform([-1, -0.5, 0.2], [1, 0.5, 3]))  # camera height; p_cam


def test_chain_reduces_to_the_paper_htm_on_flat_ground():
    for (x, y), yaw, d, h, p_cam in random_flat_cases():
        chained = chain(robot(x, y, yaw), camera_mount(d, h), at(*p_cam))[:3, 3]
        # z_Jackal is the camera's height in the map: the HTM adds none of its own.
        np.testing.assert_allclose(paper_htm(p_cam, (x, y, h), htm_theta(yaw), d), chained, atol=1e-12)
        # Eq. 1 as printed gives the same th when its Phi is the yaw plus a half turn.
        np.testing.assert_allclose(paper_htm(p_cam, (x, y, h), paper_theta(yaw + np.pi), d), chained, atol=1e-12)


def test_eq1_with_a_rep103_yaw_mirrors_objects_behind_the_robot():
    for (x, y), yaw, d, h, p_cam in random_flat_cases(10, seed=1):
        chained = chain(robot(x, y, yaw), camera_mount(d, h), at(*p_cam))[:3, 3]
        literal = paper_htm(p_cam, (x, y, h), paper_theta(yaw), d)
        np.testing.assert_allclose(literal[:2] - (x, y), -(chained[:2] - (x, y)), atol=1e-12)
        assert literal[2] == pytest.approx(chained[2])


def test_htm_is_wrong_once_the_ground_is_not_flat():
    # Robot pitched 10 deg nose-up on a ramp: the chain follows, the yaw-only HTM cannot.
    T_map_base = from_xyz_rpy((1.0, 0.0, 0.0), (0.0, -np.radians(10), 0.0))
    chained = chain(T_map_base, camera_mount(0.2, 0.3), at(0.0, 0.0, 2.0))[:3, 3]
    htm = paper_htm((0.0, 0.0, 2.0), (1.0, 0.0, 0.3), htm_theta(0.0), 0.2)
    assert chained[2] - htm[2] > 0.3  # 2.2 m * sin(10 deg) = 0.38 m higher
