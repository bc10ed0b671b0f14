"""The DOPE backends benchmark renders a frame and prints its table (no timing asserted)."""
import importlib.util

from helpers import ROOT


def test_bench_dope_backends_prints_the_table(capsys):
    spec = importlib.util.spec_from_file_location("bench_dope_backends", ROOT / "benchmarks" / "bench_dope_backends.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--repeats", "1", "--frames", "1", "--threads", "1", "--no-compile"]) == 0
    out = capsys.readouterr().out
    assert "| torch | 1 |" in out and "| torch channels-last | 1 |" in out and "| torch channels-last folded | 1 |" in out
    assert "| torch channels-last folded, refinement contiguous | 1 |" in out
    differ = [line for line in out.splitlines() if "| NO " in line]
    # every fp32 backend decodes the same detections as torch; bfloat16 and int8 need not (docs/speed.md)
    assert all(line.startswith(("| torch channels-last bf16 |", "| torch int8 |")) for line in differ), differ
    from stack.dope import int8
    from stack.dope_fpr import bf16_native

    assert ("| torch channels-last bf16 | 1 |" in out) == bf16_native()
    assert ("| torch int8 | 1 |" in out) == int8.available()
    if importlib.util.find_spec("onnxruntime") and importlib.util.find_spec("onnx"):
        assert "| onnxruntime | 1 |" in out
    else:
        assert "onnxruntime skipped" in out
