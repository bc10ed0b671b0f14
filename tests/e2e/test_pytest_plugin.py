"""The pytest plugin from a test file outside the repository: ``dopeslam_run`` runs an episode,
returns its report and folder, and runs it once per set of arguments in a pytest run."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

USER_TESTS = '''
ORACLE = "testbed.oracle_detector:OracleDetector"

def test_short_drive(dopeslam_run):
    report, out = dopeslam_run("experiment3_columns", seed=0, duration=2, detector=ORACLE)
    assert report["labels_summary"]["false_labels"] == 0 and report["seed"] == 0
    assert (out / "report.json").is_file() and (out / "map.png").is_file()
    report["labels_summary"]["false_labels"] = 99  # the caller's copy

def test_same_arguments_same_run(dopeslam_run):
    a, out_a = dopeslam_run("experiment3_columns", seed=0, duration=2, detector=ORACLE)
    b, out_b = dopeslam_run("experiment3_columns", 0, detector=ORACLE, duration=2.0)
    assert out_a == out_b and a == b and a["labels_summary"]["false_labels"] == 0
    assert len([p for p in out_a.parent.glob("dopeslam_*") if not p.is_symlink()]) == 1

def test_bad_option(dopeslam_run):
    dopeslam_run("experiment3_columns", light=5)
'''


@pytest.mark.slow
def test_fixture_from_a_test_file_outside_the_repository(pytester, monkeypatch):
    monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "1")
    pytester.makepyfile(test_user=USER_TESTS)
    assert not str(pytester.path).startswith(str(Path(__file__).resolve().parents[2]))
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", "-q")
    result.assert_outcomes(passed=2, errors=0, failed=1)
    result.stdout.fnmatch_lines(["*option 'light': expected a light level from 0 to 1, got 5*"])
