"""End-to-end tests: each runs simulated episodes (minutes). Every test collected under this folder
is marked ``slow``, so ``-m "not slow"`` selects exactly the unit tests (``tests/unit/``).

Also the fixtures that several end-to-end files share: a short drive past the default scenario's
objects."""
from __future__ import annotations

from pathlib import Path

import pytest

E2E = Path(__file__).resolve().parent


@pytest.hookimpl(tryfirst=True)  # before ``-m`` deselects by marker
def pytest_collection_modifyitems(config, items):
    # a conftest's hook sees every collected item, not only those under its folder
    for item in items:
        if E2E in item.path.parents:
            item.add_marker(pytest.mark.slow)


# --- a short drive past the default scenario's objects (test_run_e2e, test_golden_e2e, test_seams_e2e) ---

SHORT = """
extends = "{base}"
name = "columns_short"
duration = 13.0
[route]
start_pause = 0.0
speed = 0.25
waypoints = [[0.5, 0.0], [3.5, 0.0]]
[sensors]
camera_width = 320
camera_height = 240
"""


@pytest.fixture
def short_scenario(tmp_path):
    from sim.scenario import SCENES_DIR

    # a scenario may only extend files in its own folder: copy the base beside it
    base = tmp_path / "experiment3_columns.toml"
    base.write_text((SCENES_DIR / "experiment3_columns.toml").read_text())
    path = tmp_path / "columns_short.toml"
    path.write_text(SHORT.format(base=base.name))
    return path


@pytest.fixture
def short_dark_scenario(tmp_path, short_scenario):
    path = tmp_path / "columns_short_dark.toml"
    dark = SHORT.format(base="experiment3_columns.toml").replace('name = "columns_short"',
                                                                 'name = "columns_short_dark"\nlight = 0.0')
    path.write_text(dark)
    from sim.scenario import load_scenario

    assert load_scenario(path).light == 0.0  # RGB is black: only depth can label
    return path
