"""Same seed, same bytes: labels.json, the TUM files and report.json (timings aside) of two runs
of a short episode are identical."""
from __future__ import annotations

import json

import pytest

TIMINGS = {"wall_seconds", "real_time_factor", "time_split_s", "provenance"}
RATES = {"odometry_hz", "fps"}  # per wall second: timings too


def _without_timings(report: dict) -> dict:
    out = {k: v for k, v in report.items() if k not in TIMINGS}
    for section in ("odometry", "detection", "wheel_odometry"):
        if isinstance(out.get(section), dict):
            out[section] = {k: v for k, v in out[section].items() if k not in RATES}
    return out


@pytest.mark.slow
def test_two_runs_of_a_seed_write_the_same_bytes(tmp_path):
    from testbed.oracle_detector import OracleDetector
    from testbed.run import run_episode

    for name in ("a", "b"):
        run_episode(None, tmp_path / name, seed=3, duration=5.0, detector=OracleDetector())
    for f in ("labels.json", "estimate_tum.txt", "groundtruth_tum.txt"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    ra, rb = (json.loads((tmp_path / n / "report.json").read_text()) for n in ("a", "b"))
    assert ra["labels_summary"]["objects"] > 0
    assert _without_timings(ra) == _without_timings(rb)
