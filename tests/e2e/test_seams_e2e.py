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


# --- a component that breaks its contract, through the command line ------------------------------------

BROKEN_DETECTOR = '''
import numpy as np
from stack.messages import Detection

class NanAhead:
    """A user's detector whose pose went NaN (a division by a zero depth, say)."""
    def detect(self, frame):
        return [Detection("Mustard", frame.stamp, np.full((4, 4), np.nan), np.zeros((9, 2)), np.ones(9), 2.0)]
'''


@pytest.mark.slow
def test_a_broken_detector_or_no_registered_scan_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    """Whichever process or thread runs the detector, its bad detection ends the run with one line that
    names it; a run whose odometry registered no scan says so instead of an IndexError."""
    import os
    import sys

    (tmp_path / "nan_parts.py").write_text(BROKEN_DETECTOR)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    cases = [(["--detector", "nan_parts:NanAhead", "--duration", "1"],
              "dopeslam run: detector nan_parts:NanAhead: detect() on the image at t=0.000 s returned item 0: "
              "Mustard with a T_cam_obj that is a 4x4 array with NaN or inf in it"),
             (["--duration", "0.05"], "dopeslam run: experiment3_columns: the odometry registered no LiDAR scan in "
                                      "0.05 s, so there is no map")]
    try:
        for argv, says in cases:
            capsys.readouterr()
            assert main(["run", *argv, "--out", str(tmp_path / "out")]) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert err[-1].startswith(says), err[-1]
    finally:
        sys.modules.pop("nan_parts", None)
    assert not (tmp_path / "out").exists()
