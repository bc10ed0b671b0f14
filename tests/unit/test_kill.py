"""``kill -9`` at a random moment: no output stands under its final name unless it is complete, and
what the killed process left beside it is cleaned when the next one starts (``dopeslam record``,
``run`` and ``replay`` killed: ``tests/e2e/test_kill_e2e.py``)."""
from __future__ import annotations

import random
import signal
import sys

import pytest

from helpers.kill import kill_at as _kill_at
from stack.io import clean_stale, output_dir, staging_entries

WRITER = """
import sys, time
from pathlib import Path
from stack.io import output_dir
with output_dir(Path(sys.argv[1])) as d:
    for i in range(200):
        (d / f"part_{i:03d}.bin").write_bytes(b"x" * 4096)
        time.sleep(0.002)
    (d / "report.json").write_text("{}")
"""


@pytest.mark.parametrize("seed", range(4))
def test_output_folder_killed_at_random_moments(tmp_path, seed):
    out = tmp_path / "out"
    delay = random.Random(seed).uniform(0.3, 2.0)
    rc = _kill_at([sys.executable, "-c", WRITER, str(out)], delay)
    if out.exists():  # only ever complete
        assert (out / "report.json").exists() and len(list(out.glob("part_*.bin"))) == 200
    else:
        assert rc == -signal.SIGKILL
    clean_stale(out)
    assert staging_entries(out) == []
    with output_dir(out) as d:  # the next run starts clean and finishes
        (d / "report.json").write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
