"""`dopeslam sweep` resumes after a killed driver or worker and writes error rows (seed syntax, grid
expansion and cell keys: ``tests/unit/test_sweep.py``)."""
from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from helpers.cli import DOPESLAM


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
