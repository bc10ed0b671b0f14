"""The rasteriser-threads benchmark renders a tiny episode in one process per setting and prints its
table, with the images of every setting compared byte for byte (no timing asserted)."""
import importlib.util

import pytest

from helpers import ROOT


def _load():
    spec = importlib.util.spec_from_file_location("bench_render_threads", ROOT / "benchmarks" / "bench_render_threads.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_bench_render_threads_prints_the_table(capsys):
    assert _load().main(["--duration", "0.5", "--rounds", "1", "--warmup", "1", "--threads", "0,2"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| 0 |") or line.startswith("| 2 |")]
    assert len(rows) == 2, out
    assert "DIFFERENT" not in out and all("same bytes" in r for r in rows), out


def test_bench_render_threads_refuses_bad_settings(capsys):
    with pytest.raises(SystemExit) as exc:
        _load().main(["--threads", "two"])
    assert exc.value.code == 2 and "--threads" in capsys.readouterr().err
