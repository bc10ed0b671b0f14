"""The matrix runner and `dopeslam sweep`: seed syntax, grid expansion, cell keys, one-line errors
(resume after a killed driver or worker, error rows: ``tests/e2e/test_sweep_e2e.py``)."""
from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from helpers.cli import DOPESLAM
from testbed.matrix import Cell, MatrixError, SeedSyntaxError, cell_key, check_ray_address, parse_seeds
from testbed.sweep import expand, flatten


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


def test_cell_processes_side_by_side_keep_kiss_icp_in_their_own_process(monkeypatch):
    """Cells side by side already fill the cores: each keeps KISS-ICP in its own process, runs one
    detector process and renders in its own process, unless the user set DOPESLAM_ODOMETRY_PROCESS,
    DOPESLAM_DETECTOR_PROCESS or DOPESLAM_RENDER_WORKER; one cell at a time decides as ``dopeslam
    run`` does."""
    from testbed.matrix import _worker_env

    for name in ("DOPESLAM_ODOMETRY_PROCESS", "DOPESLAM_DETECTOR_PROCESS", "DOPESLAM_RENDER_WORKER"):
        monkeypatch.delenv(name, raising=False)
        assert name not in _worker_env(1)
    assert _worker_env(2)["DOPESLAM_ODOMETRY_PROCESS"] == "0"
    assert _worker_env(2)["DOPESLAM_DETECTOR_PROCESS"] == "1"  # one detector process per cell
    assert _worker_env(2)["DOPESLAM_RENDER_WORKER"] == "0"  # and no render process
    monkeypatch.setenv("DOPESLAM_RENDER_WORKER", "1")
    assert _worker_env(2)["DOPESLAM_RENDER_WORKER"] == "1"
    assert _worker_env(2)["DOPESLAM_TORCH_THREADS"] == _worker_env(1)["DOPESLAM_TORCH_THREADS"]
    monkeypatch.setenv("DOPESLAM_ODOMETRY_PROCESS", "1")
    assert _worker_env(2)["DOPESLAM_ODOMETRY_PROCESS"] == "1"


def test_flatten_keeps_scalars_only():
    assert flatten({"a": {"b": 1, "c": [1, 2], "d": {"e": None}}, "f": "x", "g": 0.5}) == {
        "a.b": 1, "a.d.e": None, "f": "x", "g": 0.5}


def test_bad_arguments_are_one_line_errors(tmp_path):
    for extra, word in [(["--seeds", "3-1"], "seeds"), (["--grid", "nope.key=1,2"], "nope"),
                        (["--jobs", "0"], "--jobs")]:
        r = subprocess.run(DOPESLAM + ["sweep", "experiment3_columns", "--out", str(tmp_path / "x")] + extra,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, (extra, r.stderr)
        assert word in r.stderr and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_ray_address_nothing_answers_at_is_one_line_before_any_work(tmp_path, capsys):
    """Ray retries a wrong address for minutes; the check says so in a moment, naming the option."""
    import socket

    from testbed.cli import main

    with socket.socket() as listening:
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        check_ray_address(f"127.0.0.1:{listening.getsockname()[1]}")  # something answers: Ray takes it from there
        with socket.socket() as closed:
            closed.bind(("127.0.0.1", 0))
            free = closed.getsockname()[1]
    for address in (None, "", "auto"):
        check_ray_address(address)
    with pytest.raises(MatrixError, match=r"^--ray-address 127\.0\.0\.1:\d+: no Ray cluster answers there"):
        check_ray_address(f"127.0.0.1:{free}")
    for bad in ("localhost", "host:port", "ray://:10001", "10.0.0.5:70000"):
        with pytest.raises(MatrixError, match="expected HOST:PORT"):
            check_ray_address(bad)
    for argv in (["sweep", "experiment3_columns", "--seeds", "0"], ["test", "smoke", "--ray"]):
        assert main([*argv, "--ray-address", f"ray://127.0.0.1:{free}", "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"dopeslam {argv[0]}: --ray-address ray://127.0.0.1:{free}: no Ray cluster answers there")
        assert "\n" not in err
    assert not (tmp_path / "out").exists()
