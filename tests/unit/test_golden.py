"""One loop for every driver: ``dopeslam run`` and the gym env's perception cache drive the same
pipeline (``stack.pipeline.DopeSlam``), so on one episode they fuse every detection with the same
pose (to the last bits KISS-ICP's threads leave); and the golden-output comparison
(``tests/golden_record.py``) finds any change.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import golden_record  # noqa: E402  (tests/golden_record.py, a script)
from test_run_e2e import short_scenario  # noqa: E402, F401 (a fixture)

# --- the comparison finds every kind of difference --------------------------------------------------


def _recording(root: Path, labels: str = '{"objects": []}', xyz=(1.0, 2.0, 3.0), fps: float = 10.0) -> Path:
    for sub in ("run", "replay"):
        d = root / sub
        d.mkdir(parents=True)
        (d / "labels.json").write_text(labels)
        (d / "estimate_tum.txt").write_text("0.0 0 0 0 0 0 0 1\n")
        (d / "groundtruth_tum.txt").write_text("0.0 0 0 0 0 0 0 1\n")
        (d / "report.json").write_text(json.dumps({"detection": {"frames": 3, "fps": fps}, "labels": []}))
    cache = root / "cache"
    cache.mkdir()
    np.savez(cache / "scene-seed0-rgb-abc.npz", det_xyz=np.array([xyz]), frame_detect_s=np.array([fps]),
             frame_T_map_base=np.full((1, 4, 4), np.nan))
    (cache / "scene-seed0-rgb-abc.thumbs.npz").write_bytes(b"")
    (cache / "scene-seed0-rgb-abc.json").write_text(json.dumps({"frames": 1, "detections": 1}))
    return root


def test_identical_recordings_compare_equal_and_timings_are_ignored(tmp_path):
    a = _recording(tmp_path / "a")
    b = _recording(tmp_path / "b", fps=99.0)  # fps and detection seconds: wall clock, not results
    assert golden_record.compare(a, b) == []  # NaN poses (frames before the first scan) equal NaN


def test_a_changed_label_file_report_value_or_cache_array_is_named(tmp_path):
    a = _recording(tmp_path / "a")
    b = _recording(tmp_path / "b", labels='{"objects": [1]}', xyz=(1.0, 2.0, 3.0 + 1e-15))
    (b / "replay" / "report.json").write_text(json.dumps({"detection": {"frames": 4}, "labels": []}))
    diffs = golden_record.compare(a, b)
    assert "run/labels.json: differs" in diffs and "replay/labels.json: differs" in diffs
    assert "replay/report.json: 'detection' differs" in diffs
    assert any(d.startswith("cache: array 'det_xyz' differs") for d in diffs)
    assert len(diffs) == 4, diffs


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
