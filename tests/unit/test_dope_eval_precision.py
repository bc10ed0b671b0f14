"""``dopeslam dope-eval`` and ``calibrate-fpr`` take the network's precision, as a run's
``detector.precision``: what they measure and calibrate is the network that will run."""
import json

import pytest

from stack.dope import int8
from testbed.cli import main


def test_dope_eval_and_calibrate_fpr_run_the_precision_asked_for(tmp_path, capsys):
    """... and like every long command they draw no progress bar where stderr is not a terminal."""
    data = tmp_path / "shards"
    assert main(["datagen", "--out", str(data), "--images", "3", "--shard-size", "3", "--workers", "1",
                 "--seed", "21"]) == 0
    assert "datagen shards" not in capsys.readouterr().err
    runs = "int8" if int8.available() else "fp32"  # int8 falls back to fp32 without quantised kernels
    table, thresholds = tmp_path / "eval.json", tmp_path / "fpr.json"
    assert main(["-q", "dope-eval", "--data", str(data), "--shards", "0:1", "--precision", "int8",
                 "--out", str(table)]) == 0
    out, err = capsys.readouterr()
    assert f"network {runs}" in out and "dope eval" not in err
    assert json.loads(table.read_text())["precision"] == runs
    assert main(["-q", "calibrate-fpr", "--data", str(data), "--shards", "0:1", "--precision", "int8",
                 "--out", str(thresholds)]) == 0
    assert json.loads(thresholds.read_text())["meta"]["precision"] == runs


def test_int8_without_a_calibration_is_one_line(tmp_path, capsys):
    import shutil

    from stack.dope_fpr import default_weights

    if not int8.available():
        pytest.skip("no x86 quantised kernels: the detector runs fp32, without a calibration to look for")
    weights = tmp_path / "mine.pt"
    shutil.copyfile(default_weights("rgb"), weights)
    assert main(["dope-eval", "--data", str(tmp_path), "--weights", str(weights), "--precision", "int8"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mine_int8.json: no such file" in err[0] and "Traceback" not in err[0]
