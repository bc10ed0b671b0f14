"""The matrix runner and `dopeslam sweep`: seed syntax, grid expansion, cell keys, resume after a
killed driver or worker, error rows."""
from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from testbed.matrix import Cell, MatrixError, SeedSyntaxError, cell_key, parse_seeds
from testbed.sweep import expand, flatten

DOPESLAM = [sys.executable, "-m", "testbed.cli"]


def test_seed_syntax():
    assert parse_seeds("0-3,20,31-33") == [0, 1, 2, 3, 20, 31, 32, 33]
    assert parse_seeds("5") == [5] and parse_seeds(7) == [7]
    assert parse_seeds("2,1,2,0-1") == [2, 1, 0]  # order kept, duplicates dropped
    for bad in ["", "a", "3-1", "-1", "1,,2", "0-9x", "1.5"]:
        with pytest.raises(SeedSyntaxError, match="seeds"):
            parse_seeds(bad)


def test_grid_expansion_order_and_overrides():
    cells, keys = expand(["experiment3_columns", "shelf_corridor"], "0-1", ["detector.stages=1,6", "light=1,0.5"],
                         ["duration=3"])
    assert keys == ["detector.stages", "light"]
    assert len(cells) == 2 * 2 * 2 * 2
    first = cells[0]
    assert (first.scenario, first.seed, first.options) == (
        "experiment3_columns", 0, {"duration": "3", "detector.stages": "1", "light": "1"})
    assert [c.seed for c in cells[:4]] == [0, 1, 0, 1]
    assert cells[2].options["light"] == "0.5" and cells[4].options["detector.stages"] == "6"
    assert {c.scenario for c in cells[8:]} == {"shelf_corridor"}
    with pytest.raises(MatrixError, match="--grid"):
        expand(["experiment3_columns"], "0", ["stages"], [])
    with pytest.raises(MatrixError, match="no_such_scenario"):
        expand(["no_such_scenario"], "0", [], [])


def test_cell_keys_stable_and_changed_by_every_input(tmp_path):
    base = Cell("experiment3_columns", 0, {"duration": "5"})
    k = cell_key(base)
    assert k == cell_key(Cell("experiment3_columns", 0, {"duration": 5.0}))  # the value, not its spelling
    assert k == cell_key(Cell("experiment3_columns", 0, {"run.duration": "5"}))  # a short name = its key
    code = "from testbed.matrix import Cell, cell_key; print(cell_key(Cell('experiment3_columns', 0, {'duration': '5'})))"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True).stdout.split()[-1] == k  # same in another interpreter
    others = [Cell("experiment3_columns", 1, {"duration": "5"}), Cell("experiment3_columns", 0, {"duration": "6"}),
              Cell("experiment3_columns", 0, {"duration": "5", "stages": "3"}),
              Cell("experiment3_columns", 0, {"duration": "5", "evidence.min_observations": "3"}),
              Cell("shelf_corridor", 0, {"duration": "5"})]
    keys = {cell_key(c) for c in others}
    assert len(keys) == len(others) and k not in keys
    from sim.scenario import resolve_path

    src = resolve_path("experiment3_columns")
    copy = tmp_path / "copy.toml"
    shutil.copy(src, copy)
    for p in src.parent.glob("*.toml"):  # what it may extend
        if p != src:
            shutil.copy(p, tmp_path / p.name)
    assert cell_key(Cell(str(copy), 0, {"duration": "5"})) == k  # the content counts, not the path
    copy.write_text(copy.read_text() + "\n# a comment changes the file\n")
    assert cell_key(Cell(str(copy), 0, {"duration": "5"})) != k
    with pytest.raises(MatrixError, match="no_section"):
        cell_key(Cell("experiment3_columns", 0, {"no_section.key": "1"}))
    with pytest.raises(MatrixError, match="stages"):
        cell_key(Cell("experiment3_columns", 0, {"stages": "9"}))


def test_perception_cache_cells_keyed_by_what_the_cache_depends_on(tmp_path):
    def cache_cell(seed=0, **kw):
        return Cell("experiment3_columns", seed, {"job": "perception-cache", "duration": 2.0,
                                                  "cache_dir": str(tmp_path), **kw})

    k = cell_key(cache_cell())
    assert k == cell_key(cache_cell()) and k != cell_key(cache_cell(1)) and k != cell_key(cache_cell(input_mode="depth"))
    assert k != cell_key(cache_cell(cache_dir=str(tmp_path / "elsewhere")))
    assert k != cell_key(Cell("experiment3_columns", 0, {"duration": 2.0}))  # a run cell of the same episode
    with pytest.raises(MatrixError, match="job"):
        cell_key(Cell("experiment3_columns", 0, {"job": "train"}))
    with pytest.raises(MatrixError, match="no_such_option"):
        cell_key(cache_cell(no_such_option=1))


def test_flatten_keeps_scalars_only():
    assert flatten({"a": {"b": 1, "c": [1, 2], "d": {"e": None}}, "f": "x", "g": 0.5}) == {
        "a.b": 1, "a.d.e": None, "f": "x", "g": 0.5}


def _rows(out: Path) -> list[dict]:
    with open(out / "results.csv") as f:
        return list(csv.DictReader(f))


def _journal(out: Path) -> list[dict]:
    p = out / "rows.jsonl"
    return [json.loads(line) for line in p.read_text().splitlines()] if p.exists() else []


def _children(pid: int) -> list[int]:
    r = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True)
    return [int(x) for x in r.stdout.split()]


@pytest.mark.slow
def test_resume_after_killed_worker_and_driver_and_error_rows(tmp_path):
    out = tmp_path / "sweep"
    args = DOPESLAM + ["sweep", "experiment3_columns", "--seeds", "0-2", "--set", "duration=1", "--jobs", "1",
                       "--out", str(out), "--no-plots", "-q"]
    env = {**os.environ, "DOPESLAM_TORCH_THREADS": "1"}
    driver = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.time() + 600
        while not _children(driver.pid) and time.time() < deadline:  # the first cell's worker
            time.sleep(0.2)
        time.sleep(2)
        for w in _children(driver.pid):
            os.kill(w, signal.SIGKILL)  # a worker dies: its cell is retried
        while len(_journal(out)) < 1 and time.time() < deadline:
            time.sleep(0.5)
        os.killpg(driver.pid, signal.SIGKILL)  # then the driver and what it ran
        driver.wait(30)
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
    first = _journal(out)
    assert len(first) in (1, 2) and all(r["status"] == "ok" for r in first)  # the retried cell finished
    done_keys = {r["key"] for r in first}
    r = subprocess.run(args, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    summary = json.loads((out / "sweep.json").read_text())
    assert summary["cells"] == 3 and summary["ok"] == 3 and summary["resumed"] == len(done_keys)
    rows = _rows(out)
    assert [int(r["seed"]) for r in rows] == [0, 1, 2] and {r["status"] for r in rows} == {"ok"}
    again = _journal(out)
    assert len(again) == 3 and {r["key"] for r in again[:len(first)]} == done_keys  # only the missing cells ran
    assert all(r["labels_summary.objects"] == "6" for r in rows)

    # a cell that cannot run is retried once, then an error row; the other cells still run
    bad = subprocess.run(DOPESLAM + ["sweep", "experiment3_columns", "--seeds", "0", "--set", "duration=1",
                                     "--grid", "detector=no_such_module_xyz:Detector,testbed.oracle_detector:OracleDetector",
                                     "--jobs", "2", "--out", str(tmp_path / "bad"), "--no-plots", "-q"],
                         env=env, capture_output=True, text=True, timeout=900)
    assert bad.returncode == 1, bad.stderr[-2000:]
    rows = _rows(tmp_path / "bad")
    assert [r["status"] for r in rows] == ["error", "ok"]
    assert "no_such_module_xyz" in rows[0]["error"]
    assert rows[1]["labels_summary.objects"] == "6"


def test_bad_arguments_are_one_line_errors(tmp_path):
    for extra, word in [(["--seeds", "3-1"], "seeds"), (["--grid", "nope.key=1,2"], "nope"),
                        (["--jobs", "0"], "--jobs")]:
        r = subprocess.run(DOPESLAM + ["sweep", "experiment3_columns", "--out", str(tmp_path / "x")] + extra,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, (extra, r.stderr)
        assert word in r.stderr and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
