"""Scenario files: the bundled ones load, and malformed ones are rejected naming file, field and expectation."""
from __future__ import annotations

import pytest

from sim.objects import CLASSES
from sim.scenario import ScenarioError, bundled_scenarios, default_scenario_path, load_scenario
from testbed.cli import main as cli_main

VALID = """\
name = "tiny"
seed = 2
duration = 5.0
light = 1.0

[room]
size = [6.0, 4.0]

[[furniture]]
kind = "pillar"
position = [1.0, 1.0]
size = [0.3, 0.3, 2.0]

[[objects]]
class = "Mustard"
position = [1.5, -1.0]
height = 0.2

[[objects]]
class = "Yogurt"
position = [2.0, -1.0]

[robot]
start = [0.0, 0.0, 0.0]

[route]
speed = 0.3
waypoints = [[1.0, 0.0], [2.0, -0.5]]
pauses = [[0, 1.0]]

[sensors]
camera_width = 320
camera_height = 240
"""

# (case, text replaced in VALID, replacement, the field the error must name)
MALFORMED = [
    ("missing table", '[room]\nsize = [6.0, 4.0]\n', "", "'room'"),
    ("unknown key", "camera_width = 320", "camera_fps = 30", "sensors.camera_fps"),
    ("wrong type", "duration = 5.0", 'duration = "five"', "duration"),
    ("light out of range", "light = 1.0", "light = 1.5", "light"),
    ("room size of three", "size = [6.0, 4.0]", "size = [6.0, 4.0, 3.0]", "room.size"),
    ("negative seed", "seed = 2", "seed = -1", "seed"),
    ("unknown object class", 'class = "Mustard"', 'class = "Banana"', "objects.0.class"),
    ("unknown furniture kind", 'kind = "pillar"', 'kind = "sofa"', "furniture.0.kind"),
    ("negative furniture size", "size = [0.3, 0.3, 2.0]", "size = [0.3, -0.3, 2.0]", "furniture.0.size"),
    ("waypoint outside the room", "[2.0, -0.5]]", "[9.0, -0.5]]", "route.waypoints.1"),
    ("waypoint too fast", "[2.0, -0.5]]", "[2.0, -0.5, 5.0]]", "route.waypoints"),
    ("robot outside the room", "start = [0.0, 0.0, 0.0]", "start = [0.0, 3.0, 0.0]", "robot.start"),
    ("robot start without yaw", "start = [0.0, 0.0, 0.0]", "start = [0.0, 0.0]", "robot.start"),
    ("pause at no waypoint", "pauses = [[0, 1.0]]", "pauses = [[5, 1.0]]", "route.pauses.0"),
    ("camera too small", "camera_width = 320", "camera_width = 10", "sensors.camera_width"),
    ("duplicate object names", 'class = "Yogurt"', 'class = "Yogurt"\nname = "Mustard"', "objects"),
    ("extends outside the folder", 'name = "tiny"', 'name = "tiny"\nextends = "../other.toml"', "extends"),
]


def test_the_valid_base_file_loads(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(VALID)
    sc = load_scenario(path)
    assert sc.name == "tiny" and sc.seed == 2 and sc.source == str(path)
    assert [o.name for o in sc.objects] == ["Mustard", "Yogurt"]
    assert sc.sensors.camera_width == 320 and sc.sensors.lidar_azimuth_steps == 1808  # defaults fill in


@pytest.mark.parametrize("case,old,new,field", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_scenario_is_rejected_naming_file_and_field(tmp_path, case, old, new, field):
    assert old in VALID
    path = tmp_path / "bad.toml"
    path.write_text(VALID.replace(old, new, 1))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    message = str(err.value)
    assert str(path) in message
    assert field in message
    assert len(message) < 400 and "\n" not in message  # one clear line, not a traceback dump


def test_invalid_toml_and_missing_files_name_the_file(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text(VALID.replace("size = [6.0, 4.0]", "size = [6.0, 4.0", 1))
    with pytest.raises(ScenarioError, match="not valid TOML") as err:
        load_scenario(path)
    assert str(path) in str(err.value)
    with pytest.raises(ScenarioError, match="file not found"):
        load_scenario(tmp_path / "absent.toml")
    with pytest.raises(ScenarioError, match="no bundled scenario"):
        load_scenario("no_such_scenario")


def test_extends_overrides_the_base_key_by_key(tmp_path):
    (tmp_path / "tiny.toml").write_text(VALID)
    child = tmp_path / "tiny_dim.toml"
    child.write_text('extends = "tiny.toml"\nname = "tiny_dim"\nlight = 0.2\n[sensors]\ncamera_rate = 5.0\n')
    sc = load_scenario(child)
    assert (sc.name, sc.light, sc.sensors.camera_rate) == ("tiny_dim", 0.2, 5.0)
    assert sc.sensors.camera_width == 320  # the rest of the table comes from the base
    assert len(sc.objects) == 2
    # an error in the base names the base file
    (tmp_path / "tiny.toml").write_text(VALID.replace("light = 1.0", "light = 2.0"))
    child.write_text('extends = "tiny.toml"\nname = "tiny_dim"\n')
    with pytest.raises(ScenarioError, match="light"):
        load_scenario(child)


def test_bundled_scenarios_load_and_the_default_is_the_papers_experiment_3():
    names = bundled_scenarios()
    assert {"experiment3_columns", "experiment3_columns_dark", "shelf_corridor"} <= set(names)
    scenarios = {n: load_scenario(n) for n in names}
    default = load_scenario(None)
    assert default_scenario_path().stem == default.name == "experiment3_columns"
    assert sorted(o.cls for o in default.objects) == sorted(CLASSES)
    # two columns either side of the path, at various heights
    ys = sorted({round(o.position[1], 2) for o in default.objects})
    assert len(ys) == 2 and ys[0] < 0 < ys[1]
    assert len({o.height for o in default.objects}) >= 4
    assert default.route.start_pause == 30.0 and default.duration == 60.0
    dark = scenarios["experiment3_columns_dark"]
    assert dark.light == 0.0
    same = {"name", "description", "light", "extends"}
    assert dark.model_dump(exclude=same) == default.model_dump(exclude=same)
    other = scenarios["shelf_corridor"]
    assert other.room.size != default.room.size
    assert [o.height for o in other.objects] != [o.height for o in default.objects]
    assert other.route.waypoints != default.route.waypoints


def test_scenes_command_lists_the_bundled_scenarios(capsys):
    assert cli_main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in bundled_scenarios():
        assert name in out
    assert "experiment3_columns (default)" in out
