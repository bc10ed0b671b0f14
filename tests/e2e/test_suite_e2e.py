"""`dopeslam test` end to end on very short episodes (the ground-truth detector, 2 s): exit codes,
the JUnit file read back with a parser, a baseline written and compared, --json on stdout (its usage
errors: ``tests/unit/test_suite_unit.py``)."""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import pytest

from helpers.cli import dopeslam

SUITE = """name = "short"
seeds = "0"
options = {{ duration = 2, detector = "testbed.oracle_detector:OracleDetector" }}
[[scenarios]]
id = "lit"
scenario = "experiment3_columns"
[scenarios.expect]
"odometry.ate_rmse_m" = "<= 0.05"
"labels_summary.false_labels" = "== 0"
"detection.frames" = ">= {frames}"
"""


@pytest.mark.slow
def test_exit_codes_junit_and_baseline(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text(SUITE.format(frames=10))
    r = dopeslam("test", good, "--out", tmp_path / "a", "--baseline", tmp_path / "base", "--update-baseline")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "cell/s" not in r.stderr  # no progress bar where stderr is not a terminal
    assert json.loads((tmp_path / "a" / "summary.json").read_text())["passed"] is True
    suite = ET.parse(tmp_path / "a" / "junit.xml").getroot().find("testsuite")
    assert (suite.get("tests"), suite.get("failures"), suite.get("errors")) == ("1", "0", "0")
    assert (tmp_path / "base" / "summary.json").is_file() and (tmp_path / "a" / "report.html").is_file()

    bad = tmp_path / "bad.toml"
    bad.write_text(SUITE.format(frames=1000))  # the one unmet expectation
    r = dopeslam("test", bad, "--out", tmp_path / "b", "--baseline", tmp_path / "base", "--junit",
                 tmp_path / "ci" / "results.xml", "--json")
    assert r.returncode == 1, r.stderr[-2000:]
    summary = json.loads(r.stdout)  # only JSON on stdout
    assert summary["passed"] is False and summary["regressions"] == []
    frames = summary["cases"][0]["cells"][0]["metrics"]
    tcs = list(ET.parse(tmp_path / "ci" / "results.xml").getroot().iter("testcase"))
    assert [tc.get("name") for tc in tcs] == ["lit seed 0"]
    (failure,) = tcs[0].findall("failure")
    cell = summary["cases"][0]["cells"][0]
    (unmet,) = [e for e in cell["expectations"] if not e["ok"]]
    n = int(unmet["measured"])
    assert 10 <= n < 1000 and "detection.frames" in frames
    assert failure.get("message") == f"detection.frames: measured {n}, expected >= 1000 (margin {n - 1000})"


@pytest.mark.slow
def test_run_json_prints_only_the_report(tmp_path):
    r = dopeslam("run", "--duration", "2", "--detector", "testbed.oracle_detector:OracleDetector", "--out",
                 tmp_path / "run", "--json")
    assert r.returncode == 0, r.stderr[-2000:]
    report = json.loads(r.stdout)
    assert report["labels_summary"]["objects"] == 6 and report["sim_seconds"] == pytest.approx(2.0)
    assert "labels_summary" in json.loads((tmp_path / "run" / "report.json").read_text())
