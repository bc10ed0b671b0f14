"""Shared fixtures: small scenario files written for a test."""
from __future__ import annotations

import textwrap
from pathlib import Path

import pytest


@pytest.fixture
def scenario_file(tmp_path):
    """Write TOML text (dedented) to ``tmp_path/<name>.toml`` and return the path."""

    def write(text: str, name: str = "scenario") -> Path:
        path = tmp_path / f"{name}.toml"
        path.write_text(textwrap.dedent(text))
        return path

    return write
