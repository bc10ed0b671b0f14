"""Bundled test suites (TOML) for `dopeslam test`."""
