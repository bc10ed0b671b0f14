"""The main job's benchmark (``benchmarks/bench_run.py``) runs a tiny episode and prints its table (no
timing asserted), with config keys from ``--set`` and the CPU of the run's child processes counted."""
import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_run.py"


def _load():
    spec = importlib.util.spec_from_file_location("bench_run", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_bench_run_prints_the_table_with_the_keyframe_gate(capsys, monkeypatch):
    monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "1")
    monkeypatch.delenv("DOPESLAM_ODOMETRY_PROCESS", raising=False)
    bench = _load()
    assert bench.main(["--duration", "2", "--set", "detector.keyframe_m=0.1", "--set", "detector.keyframe_deg=5"]) == 0
    out = capsys.readouterr().out
    assert "| repeat | sim s | wall s |" in out and "CPU s / sim s" in out
    row = [line for line in out.splitlines() if line.startswith("| 1 |")]
    assert len(row) == 1
    cpu_per_sim = float(row[0].split("|")[9])
    assert cpu_per_sim > 0
    assert row[0].rstrip().endswith("| own process |")  # the gate skips images: KISS-ICP beside the simulator
    assert bench.main(["--duration", "2", "--set", "detector.keyframe_m=-1"]) == 2
    assert "detector.keyframe_m" in capsys.readouterr().err
