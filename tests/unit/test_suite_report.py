"""Results of `dopeslam test` built from constructed reports: JUnit XML read back with a parser,
baseline comparison, summary.json and report.html parsed for its rows and images."""
from __future__ import annotations

import base64
import json
import xml.etree.ElementTree as ET
from html.parser import HTMLParser

import numpy as np
import pytest

from testbed.testing.baseline import BaselineError, compare, load_baseline
from testbed.testing.expect import parse_expectations
from testbed.testing.junit import write_junit
from testbed.testing.report_html import write_html
from testbed.testing.runner import update_baseline
from testbed.testing.suite import Case, evaluate_case


def report(labelled=6, false=0, err=0.022, ate=0.003):
    return {"labels_summary": {"labelled": labelled, "correct_labels": labelled, "false_labels": false,
                               "mean_error_m": err, "map_precision": 1.0},
            "odometry": {"ate_rmse_m": ate}, "detection": {"precision": 0.99}, "labels": [], "wall_seconds": 12.5}


def case(id_, seeds, table, rate=None):
    exps, r = parse_expectations({**table, **({} if rate is None else {"min_pass_rate": rate})}, "run", None)
    return Case(id_, "experiment3_columns", seeds, {"duration": 10.0}, exps, r)


def results(tmp_path, reports):
    import cv2

    out = []
    for i, r in enumerate(reports):
        d = tmp_path / f"cell{i}"
        d.mkdir(parents=True, exist_ok=True)
        if r is not None:
            cv2.imwrite(str(d / "map.png"), np.full((8, 8, 3), 40 * i, np.uint8))
        out.append({"cell": None, "status": "ok" if r is not None else "error",
                    "error": None if r is not None else "RuntimeError: the renderer died", "report": r,
                    "out_dir": str(d)})
    return out


def summary_of(tmp_path, cases_results, name="unit"):
    cases = [evaluate_case(c, rs) for c, rs in cases_results]
    return {"name": name, "wall_seconds": 30.0, "cases": cases, "passed": all(c["passed"] for c in cases),
            "regressions": []}


EXPECT = {"labels_summary.labelled": ">= 6", "labels_summary.false_labels": "== 0",
          "odometry.ate_rmse_m": "<= 0.01"}


def test_junit_has_one_testcase_per_seed_and_one_failure_per_unmet_expectation(tmp_path):
    lit = case("lit", [0, 1, 2], EXPECT)
    s = summary_of(tmp_path, [(lit, results(tmp_path / "a", [report(), report(labelled=4, false=1), None]))])
    assert not s["passed"]
    write_junit(tmp_path / "junit.xml", s)
    root = ET.parse(tmp_path / "junit.xml").getroot()
    suite = root.find("testsuite")
    assert (suite.get("tests"), suite.get("failures"), suite.get("errors")) == ("3", "1", "1")
    tcs = {tc.get("name"): tc for tc in suite.iter("testcase")}
    assert set(tcs) == {"lit seed 0", "lit seed 1", "lit seed 2"}
    assert tcs["lit seed 0"].find("failure") is None and tcs["lit seed 0"].find("error") is None
    msgs = sorted(f.get("message") for f in tcs["lit seed 1"].findall("failure"))
    assert msgs == ["labels_summary.false_labels: measured 1, expected == 0 (margin -1)",
                    "labels_summary.labelled: measured 4, expected >= 6 (margin -2)"]
    assert "renderer died" in tcs["lit seed 2"].find("error").get("message")
    assert float(tcs["lit seed 0"].get("time")) == 12.5


def test_min_pass_rate_tolerates_a_seed(tmp_path):
    c = case("dark", [0, 1, 2], EXPECT, rate=0.6)
    s = summary_of(tmp_path, [(c, results(tmp_path, [report(), report(false=2), report()]))])
    (cs,) = s["cases"]
    assert cs["passed"] and cs["pass_rate"] == pytest.approx(2 / 3) and [x["tolerated"] for x in cs["cells"]] == \
        [False, True, False]
    write_junit(tmp_path / "j.xml", s)
    suite = ET.parse(tmp_path / "j.xml").getroot().find("testsuite")
    assert suite.get("failures") == "0"
    assert "tolerated" in [tc for tc in suite.iter("testcase")][1].find("system-out").text
    c = case("dark", [0, 1, 2], EXPECT, rate=0.7)
    assert not summary_of(tmp_path, [(c, results(tmp_path, [report(), report(false=2), report()]))])["passed"]


def test_baseline_fails_on_a_change_for_the_worse_beyond_the_tolerance(tmp_path):
    c = case("lit", [0, 1], {"labels_summary.labelled": ">= 4"})
    before = summary_of(tmp_path, [(c, results(tmp_path / "b", [report(err=0.020, ate=0.003), report()]))])
    path = update_baseline(before, tmp_path / "base")
    base = load_baseline(path.parent)
    # seed 0: error 2.0 -> 2.9 cm (tolerance 1 cm: fine), ATE 0.3 -> 1.5 cm (tolerance 1 cm: worse);
    # seed 1: one label fewer (tolerance 0: worse), a better error is never a regression
    now = summary_of(tmp_path, [(c, results(tmp_path / "n", [report(err=0.029, ate=0.015), report(labelled=5, err=0.01)]))])
    assert now["passed"]
    regs = compare(now, base, {}, [c])
    assert sorted((r["seed"], r["path"]) for r in regs) == [(0, "odometry.ate_rmse_m"),
                                                            (1, "labels_summary.correct_labels"),
                                                            (1, "labels_summary.labelled")]
    assert not now["cases"][0]["passed"]
    d0 = now["cases"][0]["cells"][0]["deltas"]
    assert d0["labels_summary.mean_error_m"]["delta"] == pytest.approx(0.009) and not d0["labels_summary.mean_error_m"]["regression"]
    # a suite's tolerance overrides the default
    now2 = summary_of(tmp_path, [(c, results(tmp_path / "m", [report(ate=0.015), report()]))])
    assert compare(now2, base, {"odometry.ate_rmse_m": 0.05}, [c]) == []
    write_junit(tmp_path / "j.xml", now, regs)
    fails = [f for f in ET.parse(tmp_path / "j.xml").getroot().iter("failure")]
    assert len(fails) == 3 and all(f.get("type") == "regression" for f in fails)
    assert any("baseline 0.003" in f.get("message") and "tolerance 0.01" in f.get("message") for f in fails)


def test_baseline_folder_errors(tmp_path):
    with pytest.raises(BaselineError, match="no summary.json"):
        load_baseline(tmp_path)
    (tmp_path / "summary.json").write_text("{not json")
    with pytest.raises(BaselineError, match="not valid JSON"):
        load_baseline(tmp_path)
    (tmp_path / "summary.json").write_text(json.dumps({"x": 1}))
    with pytest.raises(BaselineError, match="'cases'"):
        load_baseline(tmp_path)


class _Rows(HTMLParser):
    def __init__(self):
        super().__init__()
        self.rows, self.images, self.links, self._row = [], [], [], None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "tr" and a.get("class") == "cell":
            self._row = []
            self.rows.append(self._row)
        if tag == "img":
            self.images.append(a["src"])
        if tag in ("link", "script") or (tag == "a" and "href" in a):
            self.links.append(tag)

    def handle_data(self, data):
        if self._row is not None and data.strip():
            self._row.append(data.strip())

    def handle_endtag(self, tag):
        if tag == "tr":
            self._row = None


def test_html_report_has_a_row_per_run_with_its_map_embedded(tmp_path):
    c = case("lit", [0, 1], EXPECT)
    s = summary_of(tmp_path, [(c, results(tmp_path, [report(), report(labelled=3)]))])
    base = summary_of(tmp_path, [(c, results(tmp_path / "b", [report(), report()]))])
    compare(s, base, {}, [c])
    write_html(tmp_path / "report.html", s)
    p = _Rows()
    p.feed((tmp_path / "report.html").read_text())
    assert len(p.rows) == 2 and p.rows[0][:2] == ["lit", "0"] and "pass" in p.rows[0] and "FAIL" in p.rows[1]
    assert any("labels_summary.labelled: measured 3, expected >= 6" in x for x in p.rows[1])
    assert any(x.startswith("labels_summary.labelled: -3") for x in p.rows[1])  # the delta against the baseline
    assert len(p.images) == 2 and not p.links
    for src in p.images:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
