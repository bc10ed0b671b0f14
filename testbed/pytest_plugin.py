"""pytest plugin (entry point ``pytest11``): system tests of the stack written in Python.

The fixture ``dopeslam_run(scenario=None, seed=0, **options)`` runs one simulated episode (the
options are ``dopeslam run``'s flags: ``duration``, ``light``, ``input``, ``stages``, ``fpr``,
``policy``, ``detector``, ``loop_closure``, ``weights``) and returns ``(report, out_dir)``: the
content of ``report.json`` and the folder with ``labels.xlsx``, ``map.png`` and the rest. Runs are
cached by their arguments for the whole pytest run, so several tests can look at one episode::

    def test_dark_depth(dopeslam_run):
        report, _ = dopeslam_run("experiment3_columns_dark", seed=0, input="depth", duration=20)
        assert report["labels_summary"]["false_labels"] == 0
"""
from __future__ import annotations

import copy
import json

import pytest


@pytest.fixture(scope="session")
def dopeslam_run(tmp_path_factory):
    from testbed.testing.options import OptionError, check_options, run_one

    cache: dict = {}

    def run(scenario: str | None = None, seed: int = 0, **options):
        try:
            opts = check_options(options)
        except OptionError as e:
            raise OptionError(f"dopeslam_run: {e}") from None
        key = (None if scenario is None else str(scenario), int(seed), json.dumps(opts, sort_keys=True))
        if key not in cache:
            name = "dopeslam_" + "".join(ch if ch.isalnum() else "_" for ch in str(scenario or "default"))[-40:]
            out = tmp_path_factory.mktemp(name)
            report = run_one(scenario, int(seed), opts, out)
            cache[key] = ({k: v for k, v in report.items() if not k.startswith("_")}, out)
        report, out = cache[key]
        return copy.deepcopy(report), out

    return run
