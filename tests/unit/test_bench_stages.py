"""The per-stage benchmark's meter and options (its tiny episode and table:
``tests/e2e/test_bench_stages_e2e.py``)."""
from helpers.bench_stages import load_bench as _load


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


def test_bad_png_path_is_one_line_error(capsys, tmp_path):
    for bad in (tmp_path, tmp_path / "no_such_folder" / "stages.png"):
        assert _load().main(["--duration", "0.1", "--png", str(bad)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("--png ") and str(bad) in err and "Traceback" not in err


def test_chart_draws_each_stage_beside_its_floor(tmp_path):
    """The chart of a measurement: a PNG with one bar per stage (a made-up measurement: the chart is
    under test here, the episode in tests/e2e/test_bench_stages_e2e.py)."""
    from PIL import Image

    mod = _load()
    stages = dict(zip(mod.STAGES, (3.0, 9.0, 2.0, 6.0, 30.0, 4.0, 1.0)))
    m = {"sim_s": 10.0, "cpu_s": 55.0, "stages": stages, "profile": "full", "precision": "fp32",
         "floors": {"rendering": (0.4, 0.3, 0.1), "network": 1.5, "odometry": (0.3, 0.35, 0.4)}}
    out = tmp_path / "stages.png"
    mod.plot(m, out)
    with Image.open(out) as im:
        assert im.format == "PNG" and im.size[0] > 400 and im.size[1] > 200
    assert list(tmp_path.iterdir()) == [out]  # written through a temporary file, nothing left beside it


def test_bad_config_key_is_one_line_error(capsys):
    assert _load().main(["--duration", "0.1", "--set", "detector.no_such_key=1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bench_stages: ") and "no_such_key" in err and "Traceback" not in err


def _detector(precision):
    from sim.objects import load_catalog
    from stack.dope_fpr import DopeDetector

    return DopeDetector(dims={c: s.dims for c, s in load_catalog().items()}, precision=precision, threads=1)


def test_int8_network_counts_the_float_networks_flops():
    """The FLOP counter does not see quantised convolutions: in int8 each convolution is counted from its
    shape, and that count is the float network's (the same multiply-adds)."""
    import pytest

    from stack.dope import int8

    if not int8.available():
        pytest.skip("this PyTorch has no x86 quantised kernels")
    mod = _load()
    fp32 = mod.network_flops(_detector("fp32"))
    q = _detector("int8")
    assert q.precision == "int8"
    assert mod.network_flops(q) == fp32 > 5e9  # about 7 GFLOP per 320x240 image
    rate, shape = mod.conv_gflops(q, repeats=1)
    assert rate > 0 and "conv" in shape


def test_conv_flops_by_shape_is_the_flop_counters():
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    mod = _load()
    for conv, x in ((torch.nn.Conv2d(3, 16, 3, padding=1), torch.zeros(1, 3, 24, 32)),
                    (torch.nn.Conv2d(32, 32, 7, padding=3, groups=2), torch.zeros(2, 32, 30, 40)),
                    (torch.nn.Conv2d(8, 4, 1, stride=2), torch.zeros(1, 8, 9, 9))):
        with torch.no_grad(), FlopCounterMode(display=False) as fc:
            out = conv(x)
        assert mod.conv_flops(conv, out) == fc.get_total_flops()
