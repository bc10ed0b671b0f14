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


def test_bad_config_key_is_one_line_error(capsys):
    assert _load().main(["--duration", "0.1", "--set", "detector.no_such_key=1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bench_stages: ") and "no_such_key" in err and "Traceback" not in err
