"""The experiments' options: each keeps its own input unless given one, and ``--levels`` is checked
(`dopeslam run` end to end on a short drive: ``tests/e2e/test_run_e2e.py``)."""
import pytest


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
