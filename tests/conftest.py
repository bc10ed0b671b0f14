"""Shared fixtures: small scenario files written for a test.

The suite: ``unit/`` (fast, no episode beyond a very short one) and ``e2e/`` (episodes, minutes each;
``e2e/conftest.py`` marks every test there ``slow``). ``tests/`` itself is on ``sys.path`` for both:
``helpers/`` (what a unit file and an e2e file share) and the helper scripts ``golden_record.py``,
``oracle.py`` and ``labelling_double.py``."""
from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

TESTS = str(Path(__file__).resolve().parent)
if TESTS not in sys.path:  # pytest's default import mode put it there already; importlib mode does not
    sys.path.insert(0, TESTS)


@pytest.fixture
def scenario_file(tmp_path):
    """Write TOML text (dedented) to ``tmp_path/<name>.toml`` and return the path."""

    def write(text: str, name: str = "scenario") -> Path:
        path = tmp_path / f"{name}.toml"
        path.write_text(textwrap.dedent(text))
        return path

    return write
