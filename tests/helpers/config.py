"""Shared by tests/unit/test_config.py and tests/e2e/test_config_e2e.py."""

NO_ENV: dict = {}  # an environment without a DOPESLAM_ variable
