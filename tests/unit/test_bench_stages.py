"""The per-stage benchmark runs a tiny episode and prints its table (no timing asserted)."""
import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parent.parent / "benchmarks" / "bench_stages.py"


def _load():
    spec = importlib.util.spec_from_file_location("bench_stages", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_meter_excludes_inner_stages():
    mod = _load()

    class Work:
        def outer(self):
            return self.inner() + sum(range(200_000))

        def inner(self):
            return sum(range(400_000))

    m = mod.Meter()
    m.wrap(Work, "outer", "fit_fpr")
    m.wrap(Work, "inner", "network")
    try:
        Work().outer()
    finally:
        Work.outer, Work.inner = Work.outer.__wrapped__, Work.inner.__wrapped__
    assert m.calls["fit_fpr"] == 1 and m.calls["network"] == 1
    assert m.cpu["network"] > 0 and m.cpu["fit_fpr"] > 0
    assert not hasattr(Work.outer, "__wrapped__")  # restored


def test_bad_duration_is_one_line_error(capsys):
    assert _load().main(["--duration", "-1"]) == 2
    assert "--duration" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_stages_prints_the_table(capsys, monkeypatch):
    monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "1")
    assert _load().main(["--duration", "0.5"]) == 0
    out = capsys.readouterr().out
    for row in ("rendering", "LiDAR ray casting", "KISS-ICP odometry", "DOPE network", "depth fit + FPR",
                "fusion", "**all**", "GFLOP per image", "KissICP.register_frame"):
        assert row in out, row
    from stack.dope_fpr import DopeDetector
    assert not hasattr(DopeDetector.detect, "__wrapped__")  # the benchmark put every metered method back
