"""``dopeslam experiment NAME --config/--set``: each experiment applies the config it can and refuses
the rest; a DOPE flag beats the config, which beats the experiment's own default. The ``[retire]``
section and ``--retire/--no-retire``."""
from __future__ import annotations

import sys
import types

import pytest

from stack.config import changed_keys, resolve_config
from testbed.settings import RunConfig


def test_changed_keys_lists_what_differs_from_the_defaults():
    assert changed_keys(RunConfig()) == {}
    cfg = resolve_config(None, ["stages=3", "evidence.min_observations=2", "retire.enabled=false"], environ={},
                         model=RunConfig)
    assert changed_keys(cfg) == {"detector.stages": 3, "evidence.min_observations": 2, "retire.enabled": False}


def test_episode_config_sets_the_experiments_detector_and_policy():
    from testbed.experiments import episode_config

    assert episode_config(None, "depth", 3, None) is None  # no config: the stack as shipped
    cfg = resolve_config(None, ["evidence.min_observations=2", "weights=w.pt"], environ={}, model=RunConfig)
    got = episode_config(cfg, "depth", 3, None, "last")
    assert (got.detector.input, got.detector.stages, got.detector.weights, got.store.policy) == ("depth", 3, None, "last")
    assert got.evidence.min_observations == 2 and cfg.detector.input == "rgb"  # the original is untouched


@pytest.mark.parametrize("name, setting", [("depth-grid", "odometry.voxel_size_m=0.3"),
                                           ("precision", "evidence.min_observations=2"),
                                           ("localization", "store.policy=last"),
                                           ("darkness", "run.seed=3"), ("faults", "loop_closure.enabled=true")])
def test_a_setting_the_experiment_does_not_apply_is_refused_before_anything_runs(name, setting, tmp_path, capsys):
    from testbed.cli import main

    key = setting.split("=")[0]
    assert main(["experiment", name, "--out", str(tmp_path / "x"), "--set", setting]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"key '{key}'" in err and "does not apply" in err, err
    assert not (tmp_path / "x").exists()


@pytest.fixture
def fake_experiment(monkeypatch):
    """A stand-in experiment module that records what the command gives its ``run``."""
    from testbed.commands import experiments

    got = {}
    mod = types.ModuleType("fake_experiment")
    mod.APPLIES = {"detector", "evidence"}

    def run(out_dir, input_mode="rgb", stages=6, weights=None, config=None):
        got.update(input_mode=input_mode, stages=stages, weights=weights, config=config)
        return {}

    mod.run, mod.table = run, lambda result: "table"
    monkeypatch.setitem(sys.modules, "fake_experiment", mod)
    monkeypatch.setitem(experiments.EXPERIMENTS, "localization", "fake_experiment")
    return got


def test_a_flag_beats_the_config_which_beats_the_experiments_own_default(fake_experiment, tmp_path):
    from testbed.cli import main

    out = ["experiment", "localization", "--out", str(tmp_path)]
    assert main(out) == 0
    assert fake_experiment == {"input_mode": "rgb", "stages": 6, "weights": None, "config": None}
    assert main(out + ["--set", "detector.input=depth", "--set", "evidence.min_observations=2"]) == 0
    assert fake_experiment["input_mode"] == "depth" and fake_experiment["stages"] == 6
    assert fake_experiment["config"].evidence.min_observations == 2
    f = tmp_path / "c.toml"
    f.write_text("[detector]\ninput = 'depth'\nstages = 2\n")
    assert main(out + ["--config", str(f), "--input", "rgb"]) == 0
    assert (fake_experiment["input_mode"], fake_experiment["stages"]) == ("rgb", 2)


def test_retire_settings_come_from_the_config_and_the_flag():
    from testbed.cli import build_parser
    from testbed.commands.options import config_from_args

    parse = build_parser().parse_args
    assert config_from_args(parse(["run"]), environ={}).retire.settings() is not None
    cfg = config_from_args(parse(["run", "--set", "retire.misses=4"]), environ={})
    assert cfg.retire.settings().misses == 4
    assert config_from_args(parse(["run", "--no-retire"]), environ={}).retire.settings() is None
    cfg = config_from_args(parse(["run", "--no-retire"]), environ={"DOPESLAM_RETIRE__ENABLED": "true"})
    assert cfg.retire.enabled is False  # the flag over the environment
