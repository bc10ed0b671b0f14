"""One loop for every driver: ``dopeslam run`` and the gym env's perception cache drive the same
pipeline (``stack.pipeline.DopeSlam``), so on one episode they fuse every detection with the same
pose (to the last bits KISS-ICP's threads leave). The golden-output comparison
(``tests/golden_record.py``): ``tests/unit/test_golden.py``.
"""
from __future__ import annotations

import numpy as np
import pytest

# --- run and the perception cache: the same fusion ------------------------------------------------


@pytest.mark.slow
def test_the_run_and_the_perception_cache_fuse_every_detection_with_the_same_pose(short_scenario, tmp_path):  # noqa: F811
    from sim.episode import Episode
    from sim.objects import load_catalog
    from sim.scenario import load_scenario
    from testbed.envs.perception_cache import LivePerception
    from testbed.oracle_detector import OracleDetector
    from testbed.run import run_episode

    sc = load_scenario(short_scenario)
    seed, duration = 2, 5.0
    report = run_episode(sc, tmp_path / "run", seed=seed, duration=duration, detector=OracleDetector(), write_outputs=False,
                         keep_detections=True)
    run_xyz = np.array([o.xyz for o in report["_observations"]])
    run_cam = np.array([o.cam_xyz for o in report["_observations"]])

    classes = list(load_catalog())
    with Episode(sc, seed=seed, duration=duration) as ep:
        detector = OracleDetector()
        detector.bind_episode(ep)
        live = LivePerception(ep, detector, classes, keep_images=False)
        frames = list(live.frames())
        stamps, _ = live.odom.trajectory()
    assert [f.index for f in frames] == list(range(len(frames))) and len(frames) == report["detection"]["frames"]
    cache_xyz = np.concatenate([f.detections[6]["xyz"] for f in frames])
    cache_cam = np.concatenate([f.detections[6]["cam"] for f in frames])
    assert len(run_xyz) >= 20, "the oracle should see the objects in this drive"
    # equal up to the last bits KISS-ICP's multi-threaded sums leave from one run to the next (a
    # different rule for an image's pose, e.g. extrapolated instead of interpolated, moves it by mm)
    np.testing.assert_allclose(cache_xyz, run_xyz, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cache_cam, run_cam, rtol=0, atol=1e-9)
    assert live.dropped_no_pose == report["detection"]["detections_without_pose"]
    assert len(stamps) == report["odometry"]["poses"]
