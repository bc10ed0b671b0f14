"""A short ``dopeslam run`` in a fresh interpreter: the simulator's banner stays off stdout (the command
line's other conventions: ``tests/unit/test_cli.py``)."""
import os
import subprocess
import sys

import pytest

from helpers import ROOT


@pytest.mark.slow
def test_a_short_run_prints_no_banner_on_stdout(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "DOPESLAM_TORCH_THREADS": "1"}
    r = subprocess.run([sys.executable, "-m", "testbed.cli", "run", "tests/data/labelling_small.toml", "--duration",
                        "1.5", "--out", str(tmp_path / "run")], capture_output=True, text=True, cwd=ROOT,
                       timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "pybullet build time" not in r.stdout and "EGL" not in r.stdout
    assert r.stdout.splitlines()[0].startswith("labelling_small seed")
