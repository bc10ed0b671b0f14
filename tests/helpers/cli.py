"""The ``dopeslam`` command in a fresh interpreter, shared by the sweep tests (tests/unit/test_sweep.py,
tests/e2e/test_sweep_e2e.py) and the suite tests (tests/unit/test_suite_unit.py,
tests/e2e/test_suite_e2e.py)."""
from __future__ import annotations

import os
import subprocess
import sys

DOPESLAM = [sys.executable, "-m", "testbed.cli"]


def dopeslam(*args):
    env = {**os.environ, "DOPESLAM_TORCH_THREADS": "1"}
    return subprocess.run([*DOPESLAM, *map(str, args)], capture_output=True, text=True, env=env, timeout=600)
