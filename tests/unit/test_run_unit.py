"""`dopeslam run` end to end on a short drive past the default scenario's objects, with the shipped
DOPE weights, real KISS-ICP and the real object store."""
import json

import pytest

from stack.object_store import ObjectStore
from testbed.cli import main

SHORT = """
extends = "{base}"
name = "columns_short"
duration = 13.0
[route]
start_pause = 0.0
speed = 0.25
waypoints = [[0.5, 0.0], [3.5, 0.0]]
[sensors]
camera_width = 320
camera_height = 240
"""


@pytest.fixture
def short_scenario(tmp_path):
    from sim.scenario import SCENES_DIR

    # a scenario may only extend files in its own folder: copy the base beside it
    base = tmp_path / "experiment3_columns.toml"
    base.write_text((SCENES_DIR / "experiment3_columns.toml").read_text())
    path = tmp_path / "columns_short.toml"
    path.write_text(SHORT.format(base=base.name))
    return path


@pytest.fixture
def short_dark_scenario(tmp_path, short_scenario):
    path = tmp_path / "columns_short_dark.toml"
    dark = SHORT.format(base="experiment3_columns.toml").replace('name = "columns_short"',
                                                                 'name = "columns_short_dark"\nlight = 0.0')
    path.write_text(dark)
    from sim.scenario import load_scenario

    assert load_scenario(path).light == 0.0  # RGB is black: only depth can label
    return path


@pytest.mark.slow
def test_run_in_darkness_publishes_only_labels_it_can_stand_behind(short_dark_scenario, tmp_path):
    """Depth input in the dark: the depth network often takes one object for another, so most places
    hold detections of several classes. The map must not publish those guesses: the disputed places
    stay candidates and the objects the network does tell apart are labelled, centimetres off. Seed 3
    measured the E and the Cookies (2.0 and 1.2 cm), 26 candidates, and one false label: an
    OrangeJuice that won the vote where the network sees the Yogurt and its slim stand as one
    orange-juice-sized column (docs/results.md)."""
    out = tmp_path / "dark"
    assert main(["run", str(short_dark_scenario), "--input", "depth", "--out", str(out), "--seed", "3"]) == 0
    report = json.loads((out / "report.json").read_text())
    s = report["labels_summary"]
    assert s["correct_labels"] >= 2 and s["false_labels"] <= 1, s["map_labels"]
    assert all(m["error_m"] < 0.05 for m in s["map_labels"] if m["verdict"] == "correct")
    assert s["candidates"] >= 10  # the wrong-class detections are kept, not published
    assert any("disagree" in c["reason"] or "outvoted" in c["reason"] for c in report["candidates"])


@pytest.mark.slow
def test_run_labels_the_objects_it_drives_past(short_scenario, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", str(short_scenario), "--out", str(out), "--seed", "3"]) == 0
    report = json.loads((out / "report.json").read_text())
    for key in ("scenario", "seed", "sim_seconds", "wall_seconds", "real_time_factor", "odometry", "detection",
                "labels", "labels_summary"):
        assert key in report
    assert report["odometry"]["ate_rmse_m"] < 0.05
    s = report["labels_summary"]
    assert s["objects"] == 6
    # The target for the default scenario (all labelled, no false label, mean <= 10 cm) on this
    # short drive past all six (seeds 3 and 4 measured 1.9 and 1.7 cm); a broken transform chain, pose
    # lookup or FPR puts labels metres off or lets a wrong-class detection label an object.
    assert s["labelled"] == 6, report["labels"]
    # the whole map, not the nearest label per object: no phantom or misplaced label anywhere
    assert s["labels_in_map"] == 6 and s["false_labels"] == 0 and s["map_precision"] == 1.0, s["map_labels"]
    assert s["mean_error_m"] < 0.10
    assert report["detection"]["precision"] > 0.9
    # the spreadsheet is the store: it loads back with the same objects
    from sim.objects import load_catalog

    store = ObjectStore.load(out / "labels.xlsx", dims={c: s.dims for c, s in load_catalog().items()})
    assert len(store.labels()) == s["labels_in_map"] and len(store.candidates()) == s["candidates"]
    for name in ("map.png", "estimate_tum.txt", "groundtruth_tum.txt", "labels.json"):
        assert (out / name).stat().st_size > 0
    assert "precision 100 %" in capsys.readouterr().out


def test_experiment_keeps_its_own_input_unless_given(monkeypatch):
    """``dopeslam experiment precision`` is the paper's depth-input test: no --input means depth."""
    import testbed.experiments.precision as precision
    from testbed.cli import main

    seen = {}

    def fake_run(out_dir, runs=5, seconds=60.0, weights=None, input_mode="depth", seed=0):
        seen["input_mode"] = input_mode
        raise SystemExit(0)

    monkeypatch.setattr(precision, "run", fake_run)
    with pytest.raises(SystemExit):
        main(["experiment", "precision", "--out", "unused"])
    assert seen["input_mode"] == "depth"
    with pytest.raises(SystemExit):
        main(["experiment", "precision", "--out", "unused", "--input", "rgb"])
    assert seen["input_mode"] == "rgb"


def test_darkness_levels_option_is_validated():
    from testbed.cli import build_parser

    a = build_parser().parse_args(["experiment", "darkness", "--levels", "1,0.25,0"])
    assert a.levels == (1.0, 0.25, 0.0)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["experiment", "darkness", "--levels", "1,2"])
    with pytest.raises(SystemExit):
        build_parser().parse_args(["experiment", "darkness", "--levels", "dark"])


def test_darkness_sweep_takes_one_input_when_given(monkeypatch, tmp_path):
    import testbed.experiments.darkness as darkness
    import testbed.matrix as matrix

    seen = []
    report = {"labels_summary": {"labelled": 0, "objects": 6, "labels_in_map": 0, "false_labels": 0, "missing": 6,
                                 "map_precision": None, "mean_error_m": None},
              "detection": {"precision": None, "recall": None}, "scenario": "x", "seed": 0}

    def fake_cells(cells, out_dir, jobs=1, **k):  # the sweep's cells, not their episodes
        seen.extend((c.options["input"], c.options["light"]) for c in cells)
        return [{"status": "ok", "report": report, "out_dir": str(tmp_path / "cells" / str(i))}
                for i, _ in enumerate(cells)]

    monkeypatch.setattr(matrix, "run_cells", fake_cells)
    monkeypatch.setattr(darkness, "plot", lambda *a, **k: None)
    darkness.run(tmp_path, levels=(1.0, 0.0), input_mode="rgb")
    assert seen == [("rgb", 1.0), ("rgb", 0.0)]
    seen.clear()
    darkness.run(tmp_path, levels=(0.5,))
    assert seen == [("rgb", 0.5), ("depth", 0.5)]
