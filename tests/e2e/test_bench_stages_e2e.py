"""The per-stage benchmark runs a tiny episode and prints its table (no timing asserted); its meter and
options: ``tests/unit/test_bench_stages.py``."""
import pytest

from helpers.bench_stages import load_bench as _load


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
