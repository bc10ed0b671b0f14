"""The DOPE backends benchmark renders a frame and prints its table (no timing asserted)."""
import importlib.util

from helpers import ROOT


def test_bench_dope_backends_prints_the_table(capsys):
    spec = importlib.util.spec_from_file_location("bench_dope_backends", ROOT / "benchmarks" / "bench_dope_backends.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--repeats", "1", "--frames", "1", "--threads", "1", "--no-compile"]) == 0
    out = capsys.readouterr().out
    assert "| torch | 1 |" in out and "| torch channels-last | 1 |" in out
    assert "| NO " not in out  # every backend decodes the same detections as torch
    if importlib.util.find_spec("onnxruntime") and importlib.util.find_spec("onnx"):
        assert "| onnxruntime | 1 |" in out
    else:
        assert "onnxruntime skipped" in out
