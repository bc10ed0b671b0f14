"""The stack's one config: files, environment and --set in that order, one-line errors naming the
source and the key, the written config read back, the reference in docs/ kept to the model (a short
run's config.toml and provenance: ``tests/e2e/test_config_e2e.py``)."""
from __future__ import annotations

import json

import pytest

from helpers import ROOT
from helpers.config import NO_ENV
from stack.config import (ConfigError, StackConfig, apply_sets, dump_toml, env_sets, expand_grid, parse_grid,
                          read_file, reference_markdown, resolve_config, torch_threads, write_config)
from testbed.settings import RunConfig, cache_dir


def test_defaults_are_the_shipped_stack():
    c = StackConfig()
    assert (c.detector.input, c.detector.stages, c.detector.fpr, c.detector.weights) == ("rgb", 6, True, None)
    assert c.store.policy == "robust-mean" and c.store.evidence_gate and not c.loop_closure.enabled
    assert c.evidence.min_observations == 5 and c.odometry.voxel_size_m == 0.2
    assert c.components.detector is None and c.components.odometry is None


def test_precedence_file_then_environment_then_set(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[detector]\nstages = 2\ninput = \"depth\"\n[evidence]\nmin_observations = 7\n")
    env = {"DOPESLAM_DETECTOR__STAGES": "3", "DOPESLAM_EVIDENCE__MIN_SPAN_S": "2.5", "HOME": "/x"}
    only_file = resolve_config(f, None, NO_ENV)
    assert (only_file.detector.stages, only_file.detector.input, only_file.evidence.min_observations) == (2, "depth", 7)
    with_env = resolve_config(f, None, env)
    assert with_env.detector.stages == 3 and with_env.evidence.min_span_s == 2.5
    assert with_env.detector.input == "depth"  # the file's, where the environment says nothing
    with_set = resolve_config(f, ["detector.stages=4", "stages=5"], env)  # in order: the last wins
    assert with_set.detector.stages == 5 and with_set.evidence.min_span_s == 2.5
    assert resolve_config(None, {"evidence.min_span_s": 0.5}, env).evidence.min_span_s == 0.5


def test_environment_syntax():
    env = {"DOPESLAM_LOOP_CLOSURE__FEATURES__MAX_CORNERS": "300", "dopeslam_store__policy": "last",
           "DOPESLAM_TORCH_THREADS": "1", "DOPESLAM_CACHE": "/tmp/c", "PATH": "/bin"}
    assert set(env_sets(env)) == {"loop_closure.features.max_corners", "store.policy"}
    c = resolve_config(None, None, env)
    assert c.loop_closure.features.max_corners == 300 and c.store.policy == "last"


@pytest.mark.parametrize("sets, source, key", [
    ({"detector.stagez": "3"}, "--set detector.stagez=3", "detector.stagez"),
    ({"detektor.stages": "3"}, "--set detektor.stages=3", "detektor"),
    ({"stages": "3.5"}, "--set stages=3.5", "detector.stages"),
    ({"detector.input": "ir"}, "--set detector.input=ir", "detector.input"),
    ({"evidence.vote_share": "2"}, "--set evidence.vote_share=2", "evidence.vote_share"),
    ({"detector.stages.x": "1"}, "--set detector.stages.x=1", "detector.stages"),
    ({"detector.precision": "int8", "detector.fold_stages": "false"}, "--set detector.fold_stages=false",
     "detector.precision"),  # int8 quantises the folded network only
])
def test_bad_key_or_value_named_on_one_line(sets, source, key):
    with pytest.raises(ConfigError) as e:
        apply_sets(StackConfig(), sets)
    msg = str(e.value)
    assert msg.startswith(source) and f"'{key}'" in msg and "\n" not in msg


def test_unknown_key_lists_the_section(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown key 'detector.stagez'; section 'detector' has \[.*'stages'"):
        apply_sets(StackConfig(), {"detector.stagez": "3"})
    f = tmp_path / "bad.yaml"
    f.write_text("detector:\n  stages: 3\nstore:\n  polcy: last\n")
    with pytest.raises(ConfigError, match=rf"^{f}: unknown key 'store.polcy'"):
        resolve_config(f, None, NO_ENV)
    with pytest.raises(ConfigError, match="^environment variable DOPESLAM_DETECTOR__STAGEZ: unknown key 'detector.stagez'"):
        resolve_config(None, None, {"DOPESLAM_DETECTOR__STAGEZ": "3"})


def test_bad_values_in_files_and_environment(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text("[detector]\nstages = 9\n")
    with pytest.raises(ConfigError, match=rf"^{f}: key 'detector.stages': .*less than or equal to 6, got 9"):
        resolve_config(f, None, NO_ENV)
    f.write_text("detector = 3\n")
    with pytest.raises(ConfigError, match=rf"^{f}: key 'detector': expected a section"):
        resolve_config(f, None, NO_ENV)
    f.write_text("[detector\n")
    with pytest.raises(ConfigError, match=rf"^{f}: not valid TOML"):
        resolve_config(f, None, NO_ENV)
    with pytest.raises(ConfigError, match="DOPESLAM_STORE__GATE_M: key 'store.gate_m'"):
        resolve_config(None, None, {"DOPESLAM_STORE__GATE_M": "-1"})
    with pytest.raises(ConfigError, match="expected a config file ending in .toml"):
        resolve_config(tmp_path / "c.ini", None, NO_ENV)
    with pytest.raises(ConfigError, match="file not found"):
        resolve_config(tmp_path / "none.toml", None, NO_ENV)
    with pytest.raises(ConfigError, match="expected SECTION.KEY=VALUE"):
        resolve_config(None, ["detector.stages"], NO_ENV)


def test_toml_yaml_and_json_files_read_alike(tmp_path):
    (tmp_path / "c.toml").write_text("[detector]\nstages = 3\ndepth_windows = [[0.3, 0.6]]\n"
                                     "[loop_closure]\nenabled = true\n[loop_closure.features]\nmax_corners = 200\n")
    (tmp_path / "c.yaml").write_text("detector:\n  stages: 3\n  depth_windows: [[0.3, 0.6]]\n"
                                     "loop_closure:\n  enabled: true\n  features:\n    max_corners: 200\n")
    (tmp_path / "c.json").write_text(json.dumps({"detector": {"stages": 3, "depth_windows": [[0.3, 0.6]]},
                                                 "loop_closure": {"enabled": True, "features": {"max_corners": 200}}}))
    configs = [resolve_config(tmp_path / n, None, NO_ENV) for n in ("c.toml", "c.yaml", "c.json")]
    assert configs[0] == configs[1] == configs[2]
    c = configs[0]
    assert c.detector.stages == 3 and c.detector.depth_windows == [(0.3, 0.6)]
    assert c.loop_closure.enabled and c.loop_closure.features.max_corners == 200
    assert c.loop_closure.closure_config().features.max_corners == 200
    (tmp_path / "empty.yaml").write_text("")
    assert resolve_config(tmp_path / "empty.yaml", None, NO_ENV) == StackConfig()


def test_resolved_config_round_trips(tmp_path):
    c = apply_sets(RunConfig(), {"stages": "2", "weights": "w.pt", "detector.depth_windows": "[[0.3, 0.6], [0.5, 0.9]]",
                                 "detector.input_size": "[640, 480]", "loop_closure.proximity": "never",
                                 "evidence.min_view_angle_deg": "0.25", "seed": "7", "light": "0.5",
                                 "components.detector": "my_pkg.dets:Mine", "loop_closure.features.max_corners": "99"})
    for name in ("config.toml", "config.json"):
        path = write_config(c, tmp_path / name)
        assert resolve_config(path, None, NO_ENV, RunConfig) == c
        assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was renamed
    assert resolve_config(write_config(RunConfig(), tmp_path / "d.toml"), None, NO_ENV, RunConfig) == RunConfig()
    assert "# weights = null" in dump_toml(StackConfig())
    assert read_file(tmp_path / "config.toml")["run"] == {"seed": 7, "light": 0.5, "profile": "full"}


def test_grid_and_run_keys():
    assert parse_grid("detector.stages=1,3,6") == ("detector.stages", ["1", "3", "6"])
    assert parse_grid("detector.input_size=[320,240],[640,480]")[1] == ["[320,240]", "[640,480]"]
    points = expand_grid(RunConfig(), {"stages": ["1", "6"], "light": ["0", "0.5"]})
    assert [p[0] for p in points] == [{"stages": "1", "light": "0"}, {"stages": "1", "light": "0.5"},
                                      {"stages": "6", "light": "0"}, {"stages": "6", "light": "0.5"}]
    assert [(c.detector.stages, c.run.light) for _, c in points] == [(1, 0.0), (1, 0.5), (6, 0.0), (6, 0.5)]
    with pytest.raises(ConfigError, match="--grid light=2: key 'run.light'"):
        expand_grid(RunConfig(), {"light": ["0.5", "2"]})
    with pytest.raises(ConfigError, match="key 'light': expected SECTION.KEY"):  # run keys are the harness's
        apply_sets(StackConfig(), {"light": "0.5"})
    with pytest.raises(ConfigError, match=r"unknown section 'run'; sections \['components'"):
        apply_sets(StackConfig(), {"run.light": "0.5"})
    assert RunConfig(detector={"stages": 2}).stack() == StackConfig(detector={"stages": 2})


def test_flags_are_short_forms_that_win(tmp_path):
    from testbed.cli import build_parser
    from testbed.commands.options import config_from_args

    f = tmp_path / "c.toml"
    f.write_text("[detector]\nfpr = false\nstages = 2\n[store]\npolicy = \"last\"\n[run]\nseed = 4\n")
    parse = build_parser().parse_args
    c = config_from_args(parse(["run", "--config", str(f), "--set", "stages=3"]), environ=NO_ENV)
    assert (c.detector.stages, c.detector.fpr, c.store.policy, c.run.seed) == (3, False, "last", 4)  # unset flags: no say
    c = config_from_args(parse(["run", "shelf_corridor", "--config", str(f), "--set", "stages=3", "--stages", "1",
                                "--fpr", "--seed", "2", "--loop-closure", "--policy", "best-score"]), environ=NO_ENV)
    assert (c.detector.stages, c.detector.fpr, c.run.seed, c.run.scenario) == (1, True, 2, "shelf_corridor")
    assert c.loop_closure.enabled and c.store.policy == "best-score"


def test_commands_turn_config_errors_into_exit_2(tmp_path, capsys):
    from testbed.cli import main

    assert main(["run", "--set", "detector.stagez=3", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("dopeslam run: --set detector.stagez=3: unknown key 'detector.stagez'") and "\n" not in err
    assert not (tmp_path / "r").exists()
    assert main(["score", str(tmp_path), "--set", "min_observations=x"]) == 2
    assert "key 'evidence.min_observations'" in capsys.readouterr().err
    assert main(["score", str(tmp_path), "--set", "detector.stages=3"]) == 2
    assert "only evidence.KEY" in capsys.readouterr().err
    assert main(["config", "--set", "seed=3"]) == 0
    assert "seed = 3" in capsys.readouterr().out


def test_machine_settings_from_the_environment(tmp_path):
    assert torch_threads({}) is None and torch_threads({"DOPESLAM_TORCH_THREADS": "2"}) == 2
    with pytest.raises(ConfigError, match="DOPESLAM_TORCH_THREADS: expected an integer >= 1, got 'two'"):
        torch_threads({"DOPESLAM_TORCH_THREADS": "two"})
    assert cache_dir("vocabulary", {"DOPESLAM_CACHE": str(tmp_path)}) == tmp_path / "vocabulary"
    assert (tmp_path / "vocabulary").is_dir()


def test_reference_in_docs_matches_the_model():
    doc = (ROOT / "docs" / "configuration.md").read_text()
    marker = "<!-- generated by `dopeslam config --reference`"
    assert marker in doc
    generated = doc.split(marker, 1)[1].split("\n", 1)[1].strip()
    assert generated == reference_markdown(RunConfig).strip(), \
        "docs/configuration.md is out of date: regenerate its reference with `dopeslam config --reference`"
    for section, model in RunConfig.model_fields.items():
        assert f"### `[{section}]`" in doc


def test_provenance_without_git_and_scenario_hash_follows_extends(tmp_path):
    from testbed.provenance import git_commit, provenance, scenario_sha256

    assert git_commit(tmp_path) is None
    base, child = tmp_path / "base.toml", tmp_path / "child.toml"
    base.write_text("seed = 1\n")
    child.write_text('extends = "base.toml"\n')
    h = scenario_sha256(child)
    base.write_text("seed = 2\n")
    assert scenario_sha256(child) != h and len(h) == 64
    p = provenance(seed=3, scenario=child, weights=None, thresholds=None, argv=["dopeslam", "run"])
    assert p["weights_sha256"] is None and p["seed"] == 3 and p["command"] == ["dopeslam", "run"]


def test_a_setting_a_command_does_not_apply_is_refused():
    from testbed.commands.options import REPLAY_APPLIES, refuse_unapplied

    refuse_unapplied(apply_sets(RunConfig(), {"stages": "3", "policy": "last", "seed": "2"}), REPLAY_APPLIES, "replay")
    refuse_unapplied(apply_sets(RunConfig(), {"odometry.voxel_size_m": "0.3"}), REPLAY_APPLIES, "replay")
    with pytest.raises(ConfigError, match="key 'evidence.min_observations': dopeslam replay does not apply it"):
        refuse_unapplied(apply_sets(RunConfig(), {"evidence.min_observations": "2"}), REPLAY_APPLIES, "replay")
    with pytest.raises(ConfigError, match="key 'loop_closure.top_k'"):
        refuse_unapplied(apply_sets(RunConfig(), {"loop_closure.top_k": "5"}), REPLAY_APPLIES, "replay")
