"""The looping scenario end to end at reduced length: the simulated office_loop hall, KISS-ICP odometry,
key frames into the vocabulary tree, LiDAR verification, the pose graph.

Reduced route (the full one is ~250 s): out along the south corridor, back in the dark past the start
(a revisit from the other direction: only the LiDAR-only fallback can close it), then out again in the
light (the same view as the first pass: retrieval can close it). Sensors are thinned (LiDAR columns,
camera at the key-frame rate, physics at 120 Hz) to keep the test near a minute on a shared two-core
machine. The
vocabulary tree is trained on the first pass's key frames (the paper's protocol), so the test needs no
cached vocabulary.
"""
import numpy as np
import pytest

from stack.loops.closure import LoopCloser, LoopClosureConfig
from stack.metrics import ate_rmse
from stack.loops.place_recognition import VocabularyTree, describe
from stack.transforms import inv

pytestmark = pytest.mark.slow


def reduced_office_loop():
    from sim.scenario import load_scenario

    sc = load_scenario("office_loop")
    sc.physics_hz = 120.0
    sc.route.start_pause = 0.5
    sc.route.waypoints = [[-7.0, -3.5], [-8.0, -3.5, 0.5], [-15.5, -3.5], [-16.0, -3.5, 0.5], [-10.0, -3.5]]
    sc.sensors.lidar_azimuth_steps = 512
    sc.sensors.camera_rate = 1.0  # every image is a key frame (keyframe_every = 1 below)
    sc.sensors.camera_width, sc.sensors.camera_height = 320, 240
    sc.light_schedule = [[8.0, 0.0], [17.0, 1.0]]  # dark from the first U-turn until the second
    return sc


def test_office_loop_reduced_end_to_end():
    from sim.episode import Episode
    from stack.lidar_slam import LidarOdometry
    from stack.messages import CameraFrame, LidarScan

    sc = reduced_office_loop()
    stream = []  # ("image", stamp, rgb) | ("scan", stamp, T_map_base, points_base)
    with Episode(sc, duration=26.0) as ep:
        odom = LidarOdometry(ep.T_base_velodyne)
        for msg in ep.frames():
            if isinstance(msg, LidarScan):
                T = odom.process(msg)
                if T is not None:
                    stream.append(("scan", float(odom.trajectory()[0][-1]), T, odom.last_points_base.copy()))
            elif isinstance(msg, CameraFrame):
                stream.append(("image", msg.stamp, msg.rgb))
        stamps, T_odom = odom.trajectory()
        gt = ep.T_world_base_at(stamps)
        T_world_map = ep.T_world_map
        gt_at = ep.T_world_base_at
        assert ep.follower.idx >= 4, "the reduced route was not driven"

    first_pass = [describe(m[2]) for m in stream if m[0] == "image" and m[1] < 8.0]
    tree = VocabularyTree.train([f.descriptors for f in first_pass if f is not None], branching=6, depth=3)
    cfg = LoopClosureConfig(keyframe_every=1, skip_recent_s=6.0, skip_recent_m=3.0, closure_every_m=1.0)
    lc = LoopCloser(tree, cfg)
    for m in stream:
        if m[0] == "image":
            lc.add_image(m[1], m[2])
        else:
            lc.add_scan(m[1], m[2], m[3])
    lc.finalise()
    s = lc.summary()

    # dark key frames got no description (and so proposed nothing by appearance)
    assert s["key_frames_described"] < s["key_frames"]
    assert s["loop_closures"] >= 3
    assert s["closures_by_source"]["proximity"] >= 1  # the dark revisit, closed by LiDAR alone
    for c in lc.closures:  # no false closure
        truth = inv(gt_at(c.candidate_stamp)) @ gt_at(c.query_stamp)
        assert np.linalg.norm((inv(truth) @ c.T_cand_query)[:3, 3]) < 0.3
    ate_odo = ate_rmse(T_world_map @ T_odom, gt)
    ate_lc = ate_rmse(T_world_map @ lc.correct(stamps, T_odom), gt)
    assert ate_lc <= ate_odo + 0.01, (ate_lc, ate_odo)
