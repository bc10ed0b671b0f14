"""The per-stage benchmark runs a tiny episode and prints its table (no timing asserted); its meter and
options: ``tests/unit/test_bench_stages.py``."""
import pytest

from helpers.bench_stages import load_bench as _load


@pytest.mark.slow
def test_bench_stages_prints_the_table(capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "1")
    chart = tmp_path / "stages.png"
    assert _load().main(["--duration", "0.5", "--png", str(chart)]) == 0
    out = capsys.readouterr().out
    assert chart.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"chart: {chart}" in out
    for row in ("rendering", "LiDAR ray casting", "KISS-ICP odometry", "DOPE network", "depth fit + FPR",
                "fusion", "**all**", "GFLOP per input", "fastest convolution alone", "KISS-ICP's own voxelize", "KissICP.register_frame"):
        assert row in out, row
    from kiss_icp.registration import Registration
    from stack.dope_fpr import DopeDetector
    assert not hasattr(DopeDetector.detect, "__wrapped__")  # the benchmark put every metered method back
    assert not hasattr(Registration.align_points_to_map, "__wrapped__")


@pytest.mark.slow
def test_bench_stages_meters_the_network_in_its_precision(capsys, monkeypatch):
    """``--precision bf16``: the network's floor is measured at bf16 matmul and convolution speed where it
    runs bf16, at fp32's where the CPU has no native bfloat16 (the detector then runs fp32)."""
    from stack.dope_fpr import bf16_native

    monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "1")
    assert _load().main(["--duration", "0.3", "--precision", "bf16"]) == 0
    out = capsys.readouterr().out
    runs = "bf16" if bf16_native() else "fp32"
    assert f"network {runs}" in out and f"the faster of {runs} matmul" in out


@pytest.mark.slow
def test_bench_stages_meters_the_network_in_int8(capsys, monkeypatch):
    """``--precision int8``: the network's floor is its multiply-adds at its fastest int8 convolution's
    rate (where PyTorch has no quantised kernels the detector runs fp32, and so does the floor)."""
    from stack.dope import int8

    monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "1")
    assert _load().main(["--duration", "0.3", "--precision", "int8"]) == 0
    out = capsys.readouterr().out
    if int8.available():
        assert "network int8" in out and "fastest int8 convolution alone" in out
    else:
        assert "network fp32" in out and "the faster of fp32 matmul" in out


@pytest.mark.slow
def test_bench_stages_takes_config_keys(capsys, monkeypatch):
    """``--set detector.keyframe_m=...``: the keyframe gate holds most images of a standing robot from
    the network (the network's floor counts only the images it ran on)."""
    import re

    monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "1")
    assert _load().main(["--duration", "1.5", "--set", "detector.keyframe_m=0.1",
                         "--set", "detector.keyframe_deg=5"]) == 0
    found = re.search(r"simulated, (\d+) images \((\d+) network inputs\)", capsys.readouterr().out)
    images, inputs = int(found.group(1)), int(found.group(2))
    assert 1 <= images <= 3  # of 16: the first, then one a second
    assert inputs == images  # colour input: one network input per image (the floor counts inputs)
