"""``kill -9`` at a moment, shared by tests/unit/test_kill.py and tests/e2e/test_kill_e2e.py."""
from __future__ import annotations

import os
import signal
import subprocess
import time

from helpers import ROOT as REPO


def kill_at(cmd: list[str], seconds: float, env=None) -> int:
    p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(seconds)
    if p.poll() is None:
        os.kill(p.pid, signal.SIGKILL)
    return p.wait()
