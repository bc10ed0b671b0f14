"""Loop closure: LiDAR verification accepts the same place and rejects a look-alike, the pose graph
straightens a drifted loop, and the loop closer does both online on scans of a ring corridor (and a
label made before a closure moves with it)."""
import numpy as np
import pytest

from sim.lidar import BeamPattern, BoxRayCaster
from sim.world import Box
from stack.fusion import fuse, trajectory_lookup
from stack.loops.closure import LoopCloser, LoopClosureConfig, _voxel_down, optimise_pose_graph, verify
from stack.messages import Detection
from stack.metrics import ate_rmse
from stack.transforms import from_xyz_rpy, inv, make_T

LIDAR_Z = 0.4  # velodyne above base_link in these synthetic worlds


def box(x, y, sx, sy, sz, yaw=0.0):
    return Box(from_xyz_rpy((x, y, sz / 2), (0, 0, yaw)), np.array([sx, sy, sz]) / 2)


def ring_world(seed: int = 0) -> list[Box]:
    """A 24 x 9 m hall around a 16 x 3 m block: a ring corridor 3 m wide, with furniture of random
    size along its walls."""
    b = [box(0, -4.6, 24.4, 0.2, 2.6), box(0, 4.6, 24.4, 0.2, 2.6), box(-12.1, 0, 0.2, 9.0, 2.6),
         box(12.1, 0, 0.2, 9.0, 2.6), box(0, 0, 16, 3, 2.6), box(0, 0, 24.4, 9.4, 0.02),  # floor
         Box(make_T(None, (0, 0, 2.61)), np.array([12.2, 4.7, 0.01]))]  # ceiling
    rng = np.random.default_rng(seed)
    for y_wall, sign in ((-4.5, 1), (4.5, -1), (-1.5, -1), (1.5, 1)):
        x = -11.0 + rng.uniform(0, 1)
        while x < 10.0:
            sx, sy, sz = rng.uniform(0.3, 1.6), rng.uniform(0.3, 0.6), rng.uniform(0.5, 2.2)
            b.append(box(x + sx / 2, y_wall + sign * sy / 2, sx, sy, sz))
            x += sx + rng.uniform(0.8, 2.5)
    return b


class Lidar:
    def __init__(self, boxes, azimuth_steps=450, seed=0):
        self.caster = BoxRayCaster(boxes)
        self.beams = BeamPattern.from_hardware(azimuth_steps)
        self.dirs = self.beams.directions()
        self.rng = np.random.default_rng(seed)

    def scan(self, T_world_base) -> np.ndarray:
        """Points (N, 3) in base_link (no motion during the sweep; 1 cm range noise), voxelised as the
        loop closer keeps them."""
        T_ws = T_world_base @ make_T(None, (0, 0, LIDAR_Z))
        R = T_ws[:3, :3]
        dirs_w = self.dirs @ R.T
        origins = np.broadcast_to(T_ws[:3, 3], (len(self.dirs), 3))
        az = self.beams.azimuths() + np.arctan2(R[1, 0], R[0, 0])
        r, _ = self.caster.cast(origins, dirs_w, az, 30.0)
        r = r + self.rng.standard_normal(r.shape) * 0.01
        ok = np.isfinite(r) & (r > 0.4) & (r < 30)
        return _voxel_down((self.dirs * r[..., None])[ok] + [0, 0, LIDAR_Z], LoopClosureConfig().keyframe_voxel_m)


def pose(x, y, yaw_deg):
    return from_xyz_rpy((x, y, 0.0), (0, 0, np.radians(yaw_deg)))


@pytest.fixture(scope="module")
def furnished():
    return Lidar(ring_world())


def test_same_place_is_accepted_with_the_right_relative_pose(furnished):
    T_cand, T_query = pose(-4.0, -3.0, 0), pose(-3.6, -2.8, 175)  # revisited from the other direction
    truth = inv(T_cand) @ T_query
    T_init = truth @ pose(0.35, -0.2, 4)  # the drifted odometry's guess
    v = verify(furnished.scan(T_query), furnished.scan(T_cand), T_init, path_between_m=60.0)
    assert v.accepted, v
    err = inv(truth) @ v.T_cand_query
    assert np.linalg.norm(err[:3, 3]) < 0.05
    assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 1.0
    assert v.inlier_fraction > 0.8


def test_look_alike_place_is_rejected(furnished):
    # Appearance said "same place" and the drifted odometry agrees (T_init = identity), but the query
    # is 5 m further down the same corridor: walls, floor and ceiling match, the furniture does not.
    T_cand, T_query = pose(-4.0, -3.0, 0), pose(1.0, -3.0, 0)
    v = verify(furnished.scan(T_query), furnished.scan(T_cand), np.eye(4), path_between_m=60.0)
    assert not v.accepted
    assert v.reason in ("low_overlap", "degenerate", "inconsistent_with_odometry", "high_rmse")


def test_bare_corridor_is_degenerate_and_rejected():
    # 100 m of bare corridor, its ends beyond the LiDAR's 30 m: nothing pins the position along it
    bare = Lidar([box(0, -1.6, 100, 0.2, 2.6), box(0, 1.6, 100, 0.2, 2.6), box(0, 0, 100, 3.4, 0.02),
                  Box(make_T(None, (0, 0, 2.61)), np.array([50, 1.7, 0.01]))])
    T_cand, T_query = pose(-1.0, 0.2, 0), pose(0.0, 0.2, 0)
    v = verify(bare.scan(T_query), bare.scan(T_cand), np.eye(4), path_between_m=60.0)
    assert not v.accepted and v.reason == "degenerate"


def test_a_correction_larger_than_odometry_drifts_is_rejected(furnished):
    T_cand, T_query = pose(-4.0, -3.0, 0), pose(-3.6, -2.8, 10)
    truth = inv(T_cand) @ T_query
    T_init = truth @ pose(0.6, 0.0, 0)
    cfg = LoopClosureConfig()
    assert verify(furnished.scan(T_query), furnished.scan(T_cand), T_init, 60.0, cfg).accepted
    # the same guess, but only 2 m of path between the two: 0.6 m of drift is not believable
    v = verify(furnished.scan(T_query), furnished.scan(T_cand), T_init, 2.0, cfg)
    assert not v.accepted and v.reason == "inconsistent_with_odometry"


def ring_route(laps=2, step=0.5):
    """Ground-truth poses every ``step`` m around the ring corridor's centre line (counter-clockwise)."""
    corners = [(-10.5, -3.0), (10.5, -3.0), (10.5, 3.0), (-10.5, 3.0)]
    pts = []
    for _ in range(laps):
        for a, b in zip(corners, corners[1:] + corners[:1]):
            n = int(np.hypot(b[0] - a[0], b[1] - a[1]) / step)
            for k in range(n):
                pts.append((a[0] + (b[0] - a[0]) * k / n, a[1] + (b[1] - a[1]) * k / n,
                            np.degrees(np.arctan2(b[1] - a[1], b[0] - a[0]))))
    return [pose(*p) for p in pts]


def drifted(gt, yaw_bias_deg_per_m=0.4, scale=1.02):
    """Odometry with a yaw bias and a scale error: the relative motions, corrupted and chained."""
    out = [gt[0]]
    for a, b in zip(gt[:-1], gt[1:]):
        d = inv(a) @ b
        dist = np.linalg.norm(d[:3, 3])
        d = d.copy()
        d[:3, 3] *= scale
        out.append(out[-1] @ d @ pose(0, 0, yaw_bias_deg_per_m * dist))
    return np.array(out)


def test_pose_graph_straightens_a_drifted_loop():
    gt = np.array(ring_route(laps=2, step=1.0))
    odo = drifted(gt)
    n = len(gt) // 2
    sig_o = np.array([0.02] * 3 + [0.01] * 3)
    odom_edges = [(i, i + 1, inv(odo[i]) @ odo[i + 1], sig_o) for i in range(len(gt) - 1)]
    loop_edges = [(i, i + n, inv(gt[i]) @ gt[i + n], np.array([0.05] * 3 + [0.01] * 3)) for i in range(0, n, 4)]
    T = optimise_pose_graph(odo, odom_edges, loop_edges)
    before, after = ate_rmse(odo, gt), ate_rmse(T, gt)
    assert before > 2.0
    assert after < before / 5
    np.testing.assert_allclose(T[0], gt[0], atol=1e-6)  # map stays put


def test_loop_closer_online_on_a_ring_corridor(furnished):
    gt = ring_route(laps=2, step=0.5)
    odo = drifted(np.array(gt), yaw_bias_deg_per_m=0.15, scale=1.01)
    cfg = LoopClosureConfig(scan_keyframe_every=2, proximity="always", skip_recent_s=10.0)
    lc = LoopCloser(None, cfg)
    stamps = np.arange(len(gt)) * 0.5
    for t, T_gt, T_odo in zip(stamps, gt, odo):
        lc.add_scan(t, T_odo, furnished.scan(T_gt))
    s = lc.summary()
    assert s["loop_closures"] >= 10
    for c in lc.closures:  # every accepted closure is true
        truth = inv(gt[int(round(c.candidate_stamp / 0.5))]) @ gt[int(round(c.query_stamp / 0.5))]
        assert np.linalg.norm((inv(truth) @ c.T_cand_query)[:3, 3]) < 0.1
    lc.finalise()
    corrected = lc.correct(stamps, odo)
    before, after = ate_rmse(odo, np.array(gt)), ate_rmse(corrected, np.array(gt))
    assert before > 1.0
    assert after <= before / 3, (before, after)

    # a label made on the first lap, before any closure, moves with the closures: fused again with the
    # corrected trajectory it lands near the object, with the odometry it does not
    k = int(min(c.query_stamp for c in lc.closures) / 0.5) - 4  # a little before the first closure
    T_base_cam = from_xyz_rpy((0.2, 0.0, 0.3), (-np.pi / 2, 0.0, -np.pi / 2))  # optical: z forward
    det = Detection("Mustard", stamps[k], make_T(None, (0.3, 0.1, 1.5)), np.zeros((9, 2)), np.ones(9), 1.0)
    truth = (gt[k] @ T_base_cam @ det.T_cam_obj)[:3, 3]
    with_odometry = fuse(det, (stamps, odo), T_base_cam).xyz
    with_closures = fuse(det, lambda t: lc.correct(t, trajectory_lookup(stamps, odo)(t)), T_base_cam).xyz
    assert np.linalg.norm(with_odometry - truth) > 0.5
    assert np.linalg.norm(with_closures - truth) < np.linalg.norm(with_odometry - truth) / 3
