"""World events in scenario files: parsing and validation, ground truth following them, and people
walking through seen by both the camera and the LiDAR."""
from __future__ import annotations

import numpy as np
import pytest

from sim.scenario import ScenarioError, load_scenario

BASE = """
name = "events_test"
duration = 3.0
[room]
size = [8.0, 6.0]
[[objects]]
class = "Mustard"
position = [1.5, 0.0]
height = 0.2
yaw_deg = 180
[[objects]]
class = "Cookies"
position = [1.5, 0.6]
yaw_deg = 180
[robot]
start = [0.0, 0.0, 0.0]
[route]
waypoints = [[0.3, 0.0]]
speed = 0.1
[sensors]
camera_width = 160
camera_height = 120
lidar_azimuth_steps = 360
"""


def _write(tmp_path, extra: str, name: str = "s.toml"):
    p = tmp_path / name
    p.write_text(BASE + extra)
    return p


def test_events_parse(tmp_path):
    sc = load_scenario(_write(tmp_path, """
[[events]]
kind = "move"
object = "Mustard"
at = 1.0
to = [1.5, -0.6]
height = 0.0
[[events]]
kind = "remove"
object = "Cookies"
robot_farther_than = 2.0
[[events]]
kind = "add"
class = "Yogurt"
position = [2.0, 0.0]
[[events]]
kind = "walk"
path = [[2.5, -2.0], [2.5, 2.0]]
speed = 1.2
loop = true
"""))
    assert [e.kind for e in sc.events] == ["move", "remove", "add", "walk"]
    assert sc.events[2].object == "Yogurt"  # an added object is named after its class
    assert sc.events[1].robot_farther_than == 2.0


@pytest.mark.parametrize("extra, field", [
    ('[[events]]\nkind = "move"\nobject = "Nothing"\nto = [1, 1]\n', "events.0.object"),
    ('[[events]]\nkind = "move"\nobject = "Mustard"\n', "events.0"),
    ('[[events]]\nkind = "move"\nobject = "Mustard"\nto = [9, 0]\n', "events.0.to"),
    ('[[events]]\nkind = "add"\nclass = "Teapot"\nposition = [1, 1]\n', "events.0.class"),
    ('[[events]]\nkind = "walk"\npath = [[1, 1]]\n', "events.0"),
    ('[[events]]\nkind = "jump"\n', "events.0.kind"),
    ('[[events]]\nkind = "remove"\nobject = "Mustard"\nat = -1\n', "events.0.at"),
    ('[[events]]\nkind = "add"\nclass = "Mustard"\nposition = [1, 1]\n', "events.0.object"),
])
def test_bad_events_name_the_field(tmp_path, extra, field):
    with pytest.raises(ScenarioError) as e:
        load_scenario(_write(tmp_path, extra))
    assert f"field '{field}" in str(e.value) and "s.toml" in str(e.value)


def test_walker_path_and_loop():
    from sim.events import Event, Walker

    w = Walker(Event(kind="walk", path=[[0, 0], [2, 0], [2, 1]], loop=True), body=-1, box_index=0)
    w.place_at(2.5)
    assert np.allclose(w.xy, [2, 0.5]) and np.isclose(w.heading, np.pi / 2)
    w.place_at(3.5)  # 0.5 m back from the end
    assert np.allclose(w.xy, [2, 0.5]) and np.isclose(w.heading, -np.pi / 2)
    w.event.loop = False
    w.place_at(10.0)
    assert np.allclose(w.xy, [2, 1])


def test_truth_follows_events_and_the_walker_is_seen(tmp_path):
    from sim.episode import Episode
    from stack.messages import CameraFrame, LidarScan

    sc = load_scenario(_write(tmp_path, """
[[events]]
kind = "move"
object = "Mustard"
at = 1.0
to = [1.5, -0.6]
yaw_deg = 170
[[events]]
kind = "remove"
object = "Cookies"
at = 1.5
[[events]]
kind = "add"
class = "Yogurt"
position = [2.0, 0.0]
at = 2.0
[[events]]
kind = "walk"
path = [[1.0, -2.5], [1.0, 2.5]]
speed = 2.0
at = 0.5
"""))
    with Episode(sc, seed=0, duration=3.0, renderer="tiny") as ep:
        start = {o.name: o.T_world_obj[:3, 3].copy() for o in ep.objects}
        person_px, scans = [], []
        for msg in ep.frames():
            if isinstance(msg, CameraFrame):
                person_px.append((msg.stamp, ep.occluder_fraction(msg)))
            elif isinstance(msg, LidarScan):
                scans.append(msg)
        names_then = {o.name for o in ep.objects_at(0.9)}
        names_end = {o.name for o in ep.objects}
        mustard_then = next(o for o in ep.objects_at(0.9) if o.name == "Mustard").T_world_obj[:3, 3]
        mustard_end = next(o for o in ep.objects if o.name == "Mustard").T_world_obj[:3, 3]
        assert names_then == {"Mustard", "Cookies"} and names_end == {"Mustard", "Yogurt"}
        assert np.allclose(mustard_then, start["Mustard"])
        assert np.allclose(mustard_end[:2], [1.5, -0.6], atol=1e-6) and mustard_end[2] < mustard_then[2]  # on the floor now
        assert [e["kind"] for e in ep.event_log] == ["walk", "move", "remove", "add"]
        past = ep.past_positions()
        assert {n for n, _, _ in past} == {"Mustard", "Cookies"}
        # the person crosses the camera's view (x = 1 m ahead) and the LiDAR's sweeps
        assert max(f for _, f in person_px) > 0.05
        assert max(f for t, f in person_px if t < 0.5) == 0.0  # it stands aside before it starts
        assert ep.lidar_person_points > 100
        # the LiDAR sees the world as it is: nothing left where the Cookies stood after 1.5 s
        late = scans[-1]
        pts = (late.T_world_sensor[:3, :3] @ late.points.T).T + late.T_world_sensor[:3, 3]
        near_cookies = np.linalg.norm(pts[:, :2] - start["Cookies"][:2], axis=1) < 0.05
        assert not np.any(near_cookies & (pts[:, 2] > 0.02))
