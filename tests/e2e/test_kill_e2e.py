"""``kill -9`` at a random moment of ``dopeslam record``, ``run`` and ``replay``: no output stands under
its final name unless it is complete, and the next one cleans up what the killed one left (the output
folder itself: ``tests/unit/test_kill.py``)."""
from __future__ import annotations

import os
import random
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import ROOT as REPO
from helpers.kill import kill_at as _kill_at
from stack.io import staging_entries


@pytest.mark.slow
def test_record_killed_leaves_no_bag_and_the_next_one_cleans_up(tmp_path):
    bag = tmp_path / "rec"
    env = {**os.environ, "DOPESLAM_TORCH_THREADS": "1"}
    cmd = [sys.executable, "-m", "testbed.cli", "record", "--bag", str(bag), "--duration", "4", "--seed", "2"]
    _kill_at(cmd, random.Random(7).uniform(6.0, 12.0), env)
    assert not bag.exists() or (bag / "metadata.yaml").exists()  # never a half-written bag under its name
    leftovers = [p for p in tmp_path.iterdir() if p.name.startswith(".rec.partial-")]
    from testbed.bags import BagWriter

    with BagWriter(tmp_path / "rec2", overwrite=True) as w:  # a bag beside it: cleans only its own name's
        w.write_metadata(0.0, {"x": 1})
    with BagWriter(bag, overwrite=True) as w:
        w.write_metadata(0.0, {"x": 1})
    assert not any(p.exists() for p in leftovers)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec", "rec2"]


def _complete_or_absent(out: Path, names: tuple[str, ...]) -> None:
    if out.exists():
        assert all((out / n).exists() for n in names), sorted(p.name for p in out.iterdir())


@pytest.mark.slow
def test_run_and_replay_killed_leave_complete_outputs_or_none(tmp_path):
    env = {**os.environ, "DOPESLAM_TORCH_THREADS": "1"}
    cli = [sys.executable, "-m", "testbed.cli"]
    oracle = ["--detector", "testbed.oracle_detector:OracleDetector"]
    run_out, needs = tmp_path / "run", ("report.json", "labels.json", "labels.xlsx", "estimate_tum.txt")
    rng = random.Random(11)
    _kill_at([*cli, "run", "--duration", "2", *oracle, "--out", str(run_out)], rng.uniform(4.0, 14.0), env)
    _complete_or_absent(run_out, needs)
    bag = tmp_path / "bag"
    r = subprocess.run([*cli, "record", "--bag", str(bag), "--duration", "1.5", "--seed", "3"], cwd=REPO, env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    rep_out = tmp_path / "replay"
    _kill_at([*cli, "replay", str(bag), "--out", str(rep_out)], rng.uniform(3.0, 10.0), env)
    _complete_or_absent(rep_out, ("report.json", "labels.json", "estimate_tum.txt"))
    for cmd, out in (([*cli, "run", "--duration", "2", *oracle, "--out", str(run_out)], run_out),
                     ([*cli, "replay", str(bag), "--out", str(rep_out)], rep_out)):
        r = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)  # the next run cleans up
        assert r.returncode == 0, r.stderr[-2000:]
        assert (out / "report.json").exists() and staging_entries(out) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "replay", "run"]
