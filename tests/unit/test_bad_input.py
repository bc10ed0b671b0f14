"""Bad input ends in one line on stderr and exit status 2, before any work starts; impossible
worlds are refused; outputs never destroy what is there."""
from __future__ import annotations

import shutil

import pytest

from sim.scenario import ScenarioError, default_scenario_path, load_scenario, with_overrides
from stack.errors import DopeSlamError
from testbed.cli import main


def _cli(capsys, *argv) -> tuple[int, str]:
    rc = main(list(argv))
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err[-1] if err else ""


@pytest.mark.parametrize("argv, says", [
    (["run", "--light", "5"], "--light 5.0: Input should be less than or equal to 1"),
    (["run", "--duration", "0"], "--duration 0.0: Input should be greater than 0"),
    (["run", "--duration", "nan"], "--duration nan: Input should be a finite number"),
    (["run", "--duration", "1e9"], "--duration 1000000000.0: Input should be less than or equal to 3600"),
    (["run", "--seed", "-1"], "--seed -1: Input should be greater than or equal to 0"),
    (["simulate", "--duration=-1"], "--duration -1.0: Input should be greater than 0"),
    (["odometry", "--duration", "inf"], "--duration inf: Input should be a finite number"),
    (["run", "Unicorn"], "Unicorn: no such scenario file, and no bundled scenario of that name"),
    (["navigate", "Unicorn"], "OBJECT: expected one of the scenario's objects"),
])
def test_bad_command_line_is_one_line_and_exit_2(capsys, tmp_path, argv, says):
    rc, line = _cli(capsys, *argv, "--out", str(tmp_path / "out"))
    assert rc == 2
    assert says in line and line.startswith(f"dopeslam {argv[0]}: ")
    assert not (tmp_path / "out").exists()  # nothing started


def _scene(tmp_path, text: str):
    base = default_scenario_path().read_text()
    p = tmp_path / "scene.toml"
    p.write_text(base + "\n" + text)
    return p


def _scene_replacing(tmp_path, old: str, new: str):
    text = default_scenario_path().read_text()
    assert old in text
    p = tmp_path / "scene.toml"
    p.write_text(text.replace(old, new, 1))
    return p


@pytest.mark.parametrize("extra, says", [
    ('[[furniture]]\nkind = "box"\nposition = [0.0, 0.0]\nsize = [100.0, 100.0, 1.0]\n', "reaches outside the room"),
    ('[[furniture]]\nkind = "pillar"\nposition = [0.0, 0.0]\nsize = [0.3, 0.3, 50.0]\n', "above the walls"),
])
def test_impossible_furniture_is_refused(tmp_path, extra, says):
    with pytest.raises(ScenarioError, match=says):
        load_scenario(_scene(tmp_path, extra))


def test_robot_inside_a_pillar_is_refused(tmp_path):
    sc = load_scenario(None)
    x, y = sc.robot.start[:2]
    p = _scene(tmp_path, f'[[furniture]]\nkind = "pillar"\nposition = [{x}, {y}]\nsize = [0.3, 0.3, 2.0]\n')
    with pytest.raises(ScenarioError, match="robot.start .* inside furniture"):
        load_scenario(p)


def test_object_buried_in_a_box_and_objects_in_one_place_are_refused(tmp_path):
    sc = load_scenario(None)
    o = sc.objects[0]
    box = (f'[[furniture]]\nkind = "box"\nposition = [{o.position[0]}, {o.position[1]}]\n'
           f'size = [0.3, 0.3, {o.height + 0.5}]\n')
    with pytest.raises(ScenarioError, match=r"objects.0 .* inside furniture"):
        load_scenario(_scene(tmp_path, box))
    twin = (f'[[objects]]\nclass = "{sc.objects[1].cls}"\nname = "twin"\nposition = [{o.position[0]}, {o.position[1]}]\n'
            f'height = {o.height}\n')
    with pytest.raises(ScenarioError, match="stand in the same place"):
        load_scenario(_scene(tmp_path, twin))


def test_nan_and_inf_anywhere_in_a_scene_are_refused(tmp_path):
    text = default_scenario_path().read_text()
    import re

    m = re.search(r"yaw_deg = ([-0-9.]+)", text)
    assert m
    p = _scene_replacing(tmp_path, m.group(0), "yaw_deg = nan")
    with pytest.raises(ScenarioError, match="finite"):
        load_scenario(p)


def test_overrides_go_through_the_model():
    sc = load_scenario(None)
    assert with_overrides(sc, light=0.25).light == 0.25
    assert with_overrides(sc, seed=7, duration=12.5).duration == 12.5
    with pytest.raises(ScenarioError, match="--light"):
        with_overrides(sc, light=float("nan"))
    assert issubclass(ScenarioError, DopeSlamError)


def test_bundled_scenarios_pass_the_geometry_checks():
    from sim.scenario import SCENES_DIR

    for p in sorted(SCENES_DIR.rglob("*.toml")):
        load_scenario(p)


def test_replay_never_writes_its_results_bag_over_the_input(capsys, tmp_path):
    bag = tmp_path / "field"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("precious")
    rc, line = _cli(capsys, "replay", str(bag), "--out", str(tmp_path / "o"), "--results-bag", str(bag), "--force")
    assert rc == 2 and "is (or holds, or lies inside) the input" in line
    other = tmp_path / "mine"
    other.mkdir()
    rc, line = _cli(capsys, "replay", str(bag), "--out", str(tmp_path / "o"), "--results-bag", str(other))
    assert rc == 2 and "exists already; pass --force" in line
    assert (bag / "metadata.yaml").read_text() == "precious" and other.is_dir()


def test_replay_refuses_an_out_folder_inside_the_bag(tmp_path):
    from testbed.replay import replay_bag

    bag = tmp_path / "field"
    shutil.copytree(tmp_path, bag, dirs_exist_ok=True)
    with pytest.raises(DopeSlamError, match="lies inside, the input bag"):
        replay_bag(bag, bag / "out")


def test_an_output_that_cannot_be_made_is_refused_before_any_work(capsys, tmp_path):
    blocker = tmp_path / "notes"
    blocker.write_text("the user's")
    folder = tmp_path / "folder"
    folder.mkdir()
    runs = tmp_path / "runs"
    for argv, says in [
        (["run", "--out", str(blocker / "run")], f"--out {blocker / 'run'}: {blocker} is a file, not a folder"),
        (["simulate", "--out", str(blocker)], f"--out {blocker}: exists and is not a folder"),
        (["record", "--bag", str(blocker / "ep.bag")], f"--bag {blocker / 'ep.bag'}: {blocker} is a file"),
        (["record", "--bag", str(folder), "--format", "ros2", "--force"], None),  # a ROS 2 bag is a folder: passes
        (["test", "smoke", "--out", str(runs), "--junit", str(folder)], f"--junit {folder}: is a folder"),
        (["sweep", "smoke", "--out", str(blocker / "s")], f"--out {blocker / 's'}: {blocker} is a file, not a folder"),
        (["config", "--out", str(folder)], f"--out {folder}: is a folder; expected a file name"),
        (["run", "--out", str(runs), "--store", str(folder)], f"--store {folder}: is a folder"),
    ]:
        if says is None:
            from testbed.cli import build_parser, check_output_args

            check_output_args(build_parser().parse_args(argv))
            continue
        rc, line = _cli(capsys, *argv)
        assert rc == 2 and line.startswith(f"dopeslam {argv[0]}: {says}"), (argv, line)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder", "notes"]  # no episode ran, nothing was made
    assert blocker.read_text() == "the user's" and not any(folder.iterdir())


def test_a_scenario_that_is_a_folder_or_not_text_is_one_line(capsys, tmp_path):
    binary = tmp_path / "scene.toml"
    binary.write_bytes(b"[room]\nname = '\xff\xfe'\n")
    extends = tmp_path / "child.toml"
    extends.write_text('extends = "base"\n')
    (tmp_path / "base").mkdir()
    for argv, says in [(["run", str(tmp_path)], f"{tmp_path}: is a folder; expected a scenario TOML file"),
                       (["run", str(binary)], f"{binary}: not UTF-8 text (byte 15); expected a scenario TOML file"),
                       (["test", str(binary)], f"{binary}: not UTF-8 text (byte 15)"),
                       (["run", str(extends)], f"{tmp_path / 'base'}: is a folder")]:
        rc, line = _cli(capsys, *argv, "--out", str(tmp_path / "out"))
        assert rc == 2 and line.startswith(f"dopeslam {argv[0]}: {says}"), (argv, line)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, says", [
    (["evaluate-policy", "all", "--episodes", "0"], "--episodes: expected at least 1, got 0"),
    (["evaluate-policy", "newest", "--episodes", "1"], "unknown policy 'newest'"),
    (["record", "--bag", "episode", "--format", "ros1"], "--bag episode: a ROS 1 bag's name must end in .bag"),
    (["datagen", "--slim-stand-prob", "2"], "--slim-stand-prob: expected a share from 0 to 1, got 2.0"),
    (["datagen", "--images", "0"], "--images: expected at least 1, got 0"),
    (["datagen", "--shard-size", "0"], "--shard-size: expected at least 1, got 0"),
    (["datagen", "--width", "3"], "--width: expected at least 32, got 3"),
    (["train", "--data", "d", "--crop", "100"], "--crop: expected a multiple of 8, at least 32, got 100"),
    (["train", "--data", "d", "--depth-window", "2,1"], "--depth-window: expected NEAR,FAR metres with 0 <= NEAR < FAR"),
    (["train", "--data", "d", "--lr-decay", "soon"], "--lr-decay: expected step numbers such as 5000,8000"),
    (["train", "--data", "d"], "d: no shard_*.npz/.json pairs (run `dopeslam datagen` first)"),
    (["dope-eval", "--data", "d", "--shards", "5:2"], "--shards: expected A:B, shard numbers with A < B"),
    (["calibrate-fpr", "--data", "d"], "d/shard_00000.npz: unreadable DOPE data shard"),
    (["calibrate-int8", "--data", "d"], "d: no shard_*.npz/.json pairs (run `dopeslam datagen` first)"),
    (["pose-eval", "--runs", "0"], "--runs: expected at least 1 RANSAC seed per method, got 0"),
    (["hog-detector", "eval", "--data", "d"], "d: no held-out data shards"),
])
def test_bad_option_values_are_one_line_and_exit_2(capsys, tmp_path, monkeypatch, argv, says):
    monkeypatch.chdir(tmp_path)
    rc, line = _cli(capsys, *argv, "--out", "out") if argv[0] != "record" else _cli(capsys, *argv)
    assert rc == 2 and line.startswith(f"dopeslam {argv[0]}: {says}"), line
    assert not any(tmp_path.iterdir())


def test_a_cache_folder_that_cannot_be_made_is_one_line_before_any_work(capsys, tmp_path, monkeypatch):
    blocker = tmp_path / "notes"
    blocker.write_text("x")
    monkeypatch.setenv("DOPESLAM_CACHE", str(blocker / "cache"))
    rc, line = _cli(capsys, "run", "--out", str(tmp_path / "out"))
    assert rc == 2 and line == f"dopeslam run: environment variable DOPESLAM_CACHE: {blocker / 'cache'}: {blocker} is a " \
                               "file, not a folder"
    assert not (tmp_path / "out").exists()


def test_the_cache_folder_expands_a_home_tilde(monkeypatch, tmp_path):
    """The object textures go where the rest of the cache goes, not into a folder named '~'."""
    from sim.objects import cache_dir
    from testbed.settings import cache_dir as harness_cache

    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("DOPESLAM_CACHE", "~/dopeslam-cache")
    assert cache_dir() == tmp_path / "dopeslam-cache" / "assets" and cache_dir().is_dir()
    assert harness_cache("assets", create=False) == cache_dir()
