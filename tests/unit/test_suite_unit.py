"""``dopeslam test``'s usage errors: exit status 2 and one line (the suites end to end on very short
episodes: ``tests/e2e/test_suite_e2e.py``)."""
from helpers.cli import dopeslam


def test_usage_errors_exit_2_with_one_line():
    for args in (["test", "no_such_suite"], ["test", "smoke", "--seeds", "x"], ["test", "smoke", "--set", "light=5"],
                 ["test", "smoke", "--baseline", "/nonexistent/base"], ["test", "smoke", "--update-baseline"]):
        r = dopeslam(*args)
        assert r.returncode == 2 and "Traceback" not in r.stderr, (args, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1 and r.stderr.startswith("dopeslam test: "), r.stderr
