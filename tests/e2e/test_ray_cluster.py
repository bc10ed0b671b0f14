"""The same sweep in local processes, on a local Ray runtime and on a real Ray cluster started on
127.0.0.1 (``ray start --head``, then the driver with ``--ray-address``): the same rows, timing and
provenance columns aside."""
from __future__ import annotations

import csv
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="Ray is not installed (pip install -e '.[ray]')")

from testbed.matrix import VOLATILE  # noqa: E402

pytestmark = pytest.mark.slow
DOPESLAM = [sys.executable, "-m", "testbed.cli"]
SWEEP = ["sweep", "experiment3_columns", "shelf_corridor", "--seeds", "0", "--set", "duration=1", "--no-plots", "-q"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stable_rows(out: Path) -> list[dict]:
    with open(out / "results.csv") as f:
        return [{k: v for k, v in r.items() if not VOLATILE.match(k)} for r in csv.DictReader(f)]


def _sweep(extra: list[str], out: Path, env: dict) -> list[dict]:
    r = subprocess.run(DOPESLAM + SWEEP + ["--out", str(out)] + extra, env=env, capture_output=True, text=True,
                       timeout=1200)
    assert r.returncode == 0, r.stderr[-3000:]
    return _stable_rows(out)


def test_processes_local_ray_and_a_cluster_give_the_same_rows(tmp_path):
    ray_bin = shutil.which("ray") or str(Path(sys.executable).parent / "ray")
    env = {**os.environ, "DOPESLAM_TORCH_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled"}
    procs = _sweep(["--jobs", "2"], tmp_path / "procs", env)
    assert len(procs) == 2 and {r["status"] for r in procs} == {"ok"}
    local = _sweep(["--ray"], tmp_path / "ray_local", env)
    assert local == procs
    port = _free_port()
    start = subprocess.run([ray_bin, "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port),
                            "--num-cpus", "2", "--include-dashboard", "false", "--disable-usage-stats"],
                           env=env, capture_output=True, text=True, timeout=180)
    assert start.returncode == 0, start.stderr[-2000:]
    try:
        cluster = _sweep(["--ray-address", f"127.0.0.1:{port}", "--collect-files"], tmp_path / "cluster", env)
    finally:
        subprocess.run([ray_bin, "stop", "--force"], env=env, capture_output=True, timeout=120)
    assert cluster == procs
    cells = list((tmp_path / "cluster" / "cells").iterdir())
    assert len(cells) == 2 and all((c / "labels.json").is_file() and (c / "map.png").is_file() for c in cells)
