"""``dopeslam experiment faults`` with ``--set``: every episode it runs writes the config it was given
(the other experiments' config handling: ``tests/unit/test_experiment_config.py``)."""
from __future__ import annotations

import pytest

from stack.config import resolve_config
from testbed.settings import RunConfig


@pytest.mark.slow
def test_the_faults_experiment_runs_each_episode_with_the_config(tmp_path):
    from testbed.cli import main

    out = tmp_path / "faults"
    assert main(["-q", "experiment", "faults", "--duration", "2", "--faults", "lidar_drop=0,0.5", "--stages", "3",
                 "--set", "evidence.min_observations=2", "--set", "retire.misses=4", "--out", str(out)]) == 0
    for run in ("clean", "lidar_drop_0.5"):
        cfg = resolve_config(out / "runs" / run / "config.toml", environ={}, model=RunConfig)
        assert (cfg.detector.stages, cfg.evidence.min_observations, cfg.retire.misses) == (3, 2, 4)
