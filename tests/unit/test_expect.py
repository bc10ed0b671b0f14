"""Expectations: the comparison syntax, known report paths, per-object keys, min_pass_rate, and
the errors a scenario or suite file gets before anything runs."""
from __future__ import annotations

import math

import pytest

from sim.scenario import SCENES_DIR, ScenarioError, load_scenario
from testbed.testing.expect import ExpectError, Expectation, evaluate, parse_comparison, parse_expectations
from testbed.testing.suite import SuiteError, load_plan

REPORT = {"labels_summary": {"labelled": 6, "false_labels": 0, "mean_error_m": 0.022, "map_precision": None},
          "odometry": {"ate_rmse_m": 0.003, "rpe_trans_pct": float("nan")},
          "labels": [{"object": "Mustard", "error_m": 0.031, "false_label": False, "missing": False},
                     {"object": "Yogurt", "error_m": None, "false_label": False, "missing": True}]}


@pytest.mark.parametrize("text,value,ok,margin", [
    (">= 6", 6, True, 0.0), (">= 7", 6, False, -1.0), ("> 5", 6, True, 1.0), ("> 6", 6, False, 0.0),
    ("<= 0.05", 0.022, True, 0.028), ("< 0.02", 0.022, False, -0.002), ("== 6", 6, True, 0.0),
    ("== 5", 6, False, -1.0), ("!= 5", 6, True, 1.0), ("!= 6", 6, False, 0.0), ("  >=1e-1 ", 0.2, True, 0.1),
    ("== true", 1, True, 0.0), ("== false", 1, False, -1.0), (6, 6, True, 0.0), (True, 1, True, 0.0)])
def test_every_operator_with_its_margin(text, value, ok, margin):
    op, bound = parse_comparison("labels_summary.labelled", text)
    out = evaluate(Expectation("labels_summary.labelled", op, bound), {"labels_summary": {"labelled": value}})
    assert out.ok is ok and out.measured == value
    assert out.margin == pytest.approx(margin)
    assert out.message().startswith(f"labels_summary.labelled: measured {value}, expected {op} ")


@pytest.mark.parametrize("text", ["=> 3", "> = 5", ">= abc", "about 6", "", ">=", "6", ">= nan", ">= inf", [1]])
def test_malformed_comparisons_are_errors_naming_the_key(text):
    with pytest.raises(ExpectError, match="labels_summary.labelled"):
        parse_comparison("labels_summary.labelled", text)


def test_paths_are_checked_against_the_report():
    objs = ["Mustard", "Yogurt"]
    exps, rate = parse_expectations({"labels_summary.labelled": ">= 6", "labels.Mustard.error_m": "<= 0.05",
                                     "odometry.loop_closures": ">= 1", "min_pass_rate": 0.5}, "run", objs)
    assert [str(e) for e in exps] == ["labels_summary.labelled >= 6", "labels.Mustard.error_m <= 0.05",
                                      "odometry.loop_closures >= 1"] and rate == 0.5
    for bad, what in [("labels_summary.labeled", "not a number"), ("odometry", "not a number"),
                      ("labels.Ketchup.error_m", "no object 'Ketchup'"), ("labels.Mustard.colour", "field one of"),
                      ("labels.Mustard", "labels.<object>.<field>"), ("success", "not a number")]:
        with pytest.raises(ExpectError, match=what):
            parse_expectations({bad: ">= 0"}, "run", objs)
    nav, _ = parse_expectations({"success": "== true", "final_distance_m": "<= 0.5"}, "navigate")
    assert len(nav) == 2
    with pytest.raises(ExpectError, match="navigate.json"):
        parse_expectations({"labels_summary.labelled": ">= 1"}, "navigate")


@pytest.mark.parametrize("rate", [1.5, -0.1, "0.5", True])
def test_min_pass_rate_is_a_share(rate):
    with pytest.raises(ExpectError, match="min_pass_rate"):
        parse_expectations({"min_pass_rate": rate})


def test_values_the_report_cannot_compare_fail_with_a_reason():
    def run(path, text):
        return evaluate(Expectation(path, *parse_comparison(path, text)), REPORT)

    assert run("labels.Mustard.error_m", "<= 0.05").ok and run("labels.Mustard.false_label", "== false").ok
    for path, note in [("labels.Yogurt.error_m", "None"), ("labels_summary.map_precision", "None"),
                       ("odometry.rpe_trans_pct", "nan"), ("odometry.loop_closures", "--loop-closure"),
                       ("detection.frames", "not in the report")]:
        out = run(path, ">= 0")
        assert not out.ok and out.measured is None and out.margin is None and note in out.message()
    assert run("labels.Yogurt.missing", "== true").ok
    assert not math.isnan(run("odometry.ate_rmse_m", "<= 0.01").margin)


def _scenario_with(tmp_path, expect: str):
    path = tmp_path / "my_scene.toml"
    path.write_text((SCENES_DIR / "experiment3_columns.toml").read_text() + "\n[expect]\n" + expect)
    return path


def test_a_scenario_file_carries_its_expectations(tmp_path):
    path = _scenario_with(tmp_path, '"labels_summary.labelled" = ">= 6"\n"labels.Mustard.error_m" = "<= 0.05"\n'
                                    'min_pass_rate = 0.8\n')
    assert load_scenario(path).expect["min_pass_rate"] == 0.8
    plan = load_plan([str(path)], seeds="0-2,7")
    (case,) = plan.cases
    assert case.seeds == [0, 1, 2, 7] and case.min_pass_rate == 0.8 and len(case.expectations) == 2


def test_scenario_errors_name_the_file_and_the_key(tmp_path):
    path = _scenario_with(tmp_path, '"labels_summary.labelled" = "at least 6"\n')
    with pytest.raises(ScenarioError, match=r"my_scene.toml: field 'expect.*labels_summary.labelled"):
        load_scenario(path)
    path = _scenario_with(tmp_path, '"labels_summary.labeled" = ">= 6"\n')
    with pytest.raises(SuiteError, match=r"my_scene.toml: expect 'labels_summary.labeled': not a number"):
        load_plan([str(path)])
    path = _scenario_with(tmp_path, '"labels.Ketchup.error_m" = "<= 0.05"\n')
    with pytest.raises(SuiteError, match=r"my_scene.toml: .*no object 'Ketchup'"):
        load_plan([str(path)])


def test_suite_errors_name_the_file_and_the_key(tmp_path):
    def suite(text):
        p = tmp_path / "suite.toml"
        p.write_text(text)
        return str(p)

    cases = [
        ('[[scenarios]]\nscenario = "experiment3_columns"\n[scenarios.expect]\n"odometry.ate" = "<= 1"\n',
         r"suite.toml: scenarios.0: expect 'odometry.ate'"),
        ('[[scenarios]]\nscenario = "experiment3_columns"\noptions = { light = 5 }\n',
         r"suite.toml: scenarios.0: option 'light': expected a light level from 0 to 1, got 5"),
        ('[[scenarios]]\nscenario = "experiment3_columns"\noptions = { speed = 1 }\n', r"option 'speed': not an option"),
        ('[[scenarios]]\nscenario = "nowhere"\n', r"nowhere: no such scenario"),
        ('[[scenarios]]\nscenario = "experiment3_columns"\nseeds = "3-1"\n', r"scenarios.0: field 'seeds'"),
        ('[[scenarios]]\nscenario = "experiment3_columns"\ncolour = 1\n', r"scenarios.0: field 'colour'"),
        ('[[scenarios]]\nscenario = "experiment3_columns"\noptions = { job = "navigate" }\n', r"option 'object'"),
        ('nme = "x"\n[[scenarios]]\nscenario = "experiment3_columns"\n', r"suite.toml: field 'nme'"),
        ('name = "x"\n', r"suite.toml: field 'scenarios'"),
        ('[[scenarios]\n', r"suite.toml: not valid TOML"),
    ]
    for text, what in cases:
        with pytest.raises(SuiteError, match=what):
            load_plan([suite(text)])
    with pytest.raises(SuiteError, match="no such suite or scenario"):
        load_plan(["no_such_thing"])
    with pytest.raises(SuiteError, match="--set 'light=5'.*|option 'light'"):
        load_plan(["smoke"], settings=["light=5"])
    with pytest.raises(SuiteError, match="--set 'speed=1'"):
        load_plan(["smoke"], settings=["speed=1"])
    with pytest.raises(SuiteError, match="--seeds"):
        load_plan(["smoke"], seeds="a-b")


def test_bundled_suites_load_and_set_options():
    plan = load_plan(["smoke", "mission"], settings=["duration=5", "fpr=false"])
    ids = [c.id for c in plan.cases]
    assert len(ids) == len(set(ids)) and "navigate-Mustard" in ids
    for c in plan.cases:
        if c.options.get("job") == "navigate":
            assert "duration" not in c.options
        else:
            assert c.options["duration"] == 5.0 and c.options["fpr"] is False
    assert next(c for c in plan.cases if c.id == "long-loop").options["loop_closure"] is True


def test_stack_settings_pass_through_to_the_config():
    plan = load_plan(["smoke"], settings=["evidence.min_observations=3"])
    assert all(c.options["evidence.min_observations"] == "3" for c in plan.cases)
    with pytest.raises(SuiteError, match="evidence.min_observationz|min_observationz"):
        load_plan(["smoke"], settings=["evidence.min_observationz=3"])
    with pytest.raises(SuiteError, match="evidence.min_observations"):
        load_plan(["smoke"], settings=["evidence.min_observations=many"])
