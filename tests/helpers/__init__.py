"""What the test files share: fixtures and helpers that a subject's unit tests (``tests/unit/``) and
its end-to-end tests (``tests/e2e/``) both use live here, one module per subject, never copied.

``tests/`` is on ``sys.path`` (``tests/conftest.py`` puts it there), so a test imports them as
``from helpers import ROOT`` or ``from helpers.gym_env import env_kwargs``.
"""
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]  # tests/
ROOT = TESTS.parent  # the repository
DATA = TESTS / "data"  # the test scenes and data files
