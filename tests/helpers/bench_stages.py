"""``benchmarks/bench_stages.py`` loaded as a module, for tests/unit/test_bench_stages.py and
tests/e2e/test_bench_stages_e2e.py."""
import importlib.util

from helpers import ROOT

BENCH = ROOT / "benchmarks" / "bench_stages.py"


def load_bench():
    spec = importlib.util.spec_from_file_location("bench_stages", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
