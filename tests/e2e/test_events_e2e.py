"""A world event end to end: an object moved in view is labelled at its new place and its old label
retired (events in scenario files, and ground truth following them: ``tests/unit/test_events.py``)."""
from __future__ import annotations

import pytest


MOVED = """
name = "moved_short"
duration = 8.0
[room]
size = [8.0, 6.0]
[[furniture]]
kind = "pillar"
position = [-2.5, 1.5]
size = [0.4, 0.4, 2.0]
[[furniture]]
kind = "box"
position = [3.0, -1.8]
size = [0.8, 0.8, 0.8]
[[objects]]
class = "Mustard"
position = [1.6, -0.4]
height = 0.2
yaw_deg = 180
[[objects]]
class = "Cookies"
position = [2.0, 0.0]
yaw_deg = 180
[robot]
start = [0.0, 0.0, 0.0]
[route]
waypoints = [[0.6, 0.0]]
speed = 0.1
[sensors]
camera_width = 320
camera_height = 240
lidar_azimuth_steps = 900
[[events]]
kind = "move"
object = "Mustard"
at = 3.0
to = [1.6, 0.4]
height = 0.2
yaw_deg = 180
"""


@pytest.mark.slow
def test_moved_object_relabelled_and_old_label_retired(tmp_path):
    """End to end (oracle detections, the rest the real stack): the Mustard moved 0.8 m in view is
    labelled at its new place, its old label retired (not stale), no false label."""
    from testbed.oracle_detector import OracleDetector
    from testbed.run import run_episode

    p = tmp_path / "moved.toml"
    p.write_text(MOVED)
    rep = run_episode(p, tmp_path / "run", seed=0, detector=OracleDetector(), write_outputs=False)
    s = rep["labels_summary"]
    mustard = next(r for r in rep["labels"] if r["object"] == "Mustard")
    assert mustard["error_m"] is not None and mustard["error_m"] < 0.10
    assert s["false_labels"] == 0 and s["stale_labels"] == 0
    (moved,) = rep["moved_objects"]
    assert moved["labelled"] and moved["relabel_delay_s"] is not None and moved["relabel_delay_s"] < 4.0
    assert len(rep["retirement"]["retired"]) == 1
    # without retirement the old place keeps a stale label
    rep2 = run_episode(p, tmp_path / "run2", seed=0, detector=OracleDetector(), write_outputs=False, retire=False)
    assert rep2["labels_summary"]["stale_labels"] == 1
