"""The run profiles: ``full`` renders everything at the scenario's rates; ``fast`` halves the camera
rate and skips the segmentation image, so the per-image recall is not scored."""
from __future__ import annotations

import numpy as np
import pytest

from sim.episode import Episode
from sim.scenario import ScenarioError, load_scenario
from stack.config import ConfigError, resolve_config
from stack.messages import CameraFrame
from testbed.run import DetectionLog, score_detections
from testbed.settings import RunConfig, profile_sensors

ROOM = """
name = "profile_room"
duration = 0.5
[room]
size = [6.0, 6.0]
[[objects]]
class = "Mustard"
position = [1.0, 0.0]
[robot]
start = [0.0, 0.0, 0.0]
[route]
start_pause = 100.0
waypoints = [[1.0, 0.0]]
[sensors]
lidar = false
"""


@pytest.fixture
def room(tmp_path):
    path = tmp_path / "room.toml"
    path.write_text(ROOM)
    return load_scenario(str(path))


def test_profile_sensors():
    assert profile_sensors("full", 10.0, False) == (10.0, True)
    assert profile_sensors("fast", 10.0, False) == (5.0, False)
    assert profile_sensors("fast", 6.0, True) == (3.0, True)  # people walking: the segmentation stays


def test_profile_is_a_validated_config_key():
    assert resolve_config(None, ["profile=fast"], {}, RunConfig).run.profile == "fast"
    assert resolve_config(None, [], {}, RunConfig).run.profile == "full"
    with pytest.raises(ConfigError, match="run.profile.*'full' or 'fast'"):
        resolve_config(None, ["run.profile=quick"], {}, RunConfig)


def test_camera_rate_override_is_validated(room):
    with pytest.raises(ScenarioError, match="camera rate"):
        Episode(room, camera_rate=0.0)


def test_fast_frames_same_pixels_no_segmentation(room):
    """Half the frames; each rendered frame has the same colour and depth as the full profile's frame
    at the same time would have without noise; no segmentation, so image_truth has no visible fraction."""
    room.sensors.noise = False
    with Episode(room) as ep:
        full = [m for m in ep.frames() if isinstance(m, CameraFrame)]
    with Episode(room, camera_rate=5.0, segmentation=False) as ep:
        fast = [m for m in ep.frames() if isinstance(m, CameraFrame)]
        truths = ep.image_truth(fast[0])
    assert len(full) == 6 and len(fast) == 3
    assert [f.stamp for f in fast] == pytest.approx([f.stamp for f in full[::2]])
    for a, b in zip(full[::2], fast):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth_m, b.depth_m)
        assert a.extra["segmentation"] is not None and b.extra["segmentation"] is None
    assert truths[0]["in_front"] and truths[0]["visible_fraction"] is None


def test_recall_not_scored_without_visible_fractions():
    truth = {"cls": "Mustard", "in_front": True, "T_cam_obj": np.eye(4), "distance_m": 1.0}
    scored, unscored = DetectionLog(), DetectionLog()
    score_detections(scored, [], [{**truth, "visible_fraction": 0.9}])
    score_detections(unscored, [], [{**truth, "visible_fraction": None}])
    assert scored.summary()["instances"] == 1 and scored.summary()["recall"] == 0.0
    s = unscored.summary()
    assert s["instances"] is None and s["correct"] is None and s["recall"] is None
