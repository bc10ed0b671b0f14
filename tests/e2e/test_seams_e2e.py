"""The ground-truth detector is the upper bound of ``dopeslam run`` (the seams for other people's
components: ``tests/unit/test_seams.py``)."""
from __future__ import annotations

import json

import pytest

from testbed.cli import main

# --- the upper bound: dopeslam run with the ground-truth detector -------------------------------------


@pytest.mark.slow
def test_the_ground_truth_detector_puts_every_label_within_2_cm(short_scenario, tmp_path):  # noqa: F811
    out = tmp_path / "oracle"
    assert main(["run", str(short_scenario), "--detector", "testbed.oracle_detector:OracleDetector",
                 "--out", str(out), "--seed", "3"]) == 0
    report = json.loads((out / "report.json").read_text())
    s = report["labels_summary"]
    assert report["detector"] == "testbed.oracle_detector:OracleDetector"
    assert s["labelled"] == 6 and s["false_labels"] == 0, s["map_labels"]
    errors = [r["error_m"] for r in report["labels"]]
    assert max(errors) < 0.02, errors
    assert report["detection"]["precision"] == 1.0
