"""The configuration options every command that runs the stack shares: ``--config FILE`` and
``--set SECTION.KEY=VALUE`` (repeatable), and the command's own flags (``--input``, ``--stages``,
``--policy``, ``--seed``, ...) as short forms of ``--set``.

Precedence, each over the one before: defaults < ``--config`` file < ``DOPESLAM_SECTION__KEY``
environment variables < ``--set`` < the command's own flags (only those given). See
:mod:`stack.config` and ``docs/configuration.md``.
"""
from __future__ import annotations

import argparse
import sys

from stack.config import ConfigError, resolve_config
from testbed.settings import RunConfig

# argparse destination -> config key, for the flags that are short forms of --set
FLAG_KEYS = {
    "scenario": "run.scenario", "seed": "run.seed", "light": "run.light", "duration": "run.duration",
    "input_mode": "detector.input", "stages": "detector.stages", "fpr": "detector.fpr",
    "weights": "detector.weights", "dope_every": "detector.every",
    "policy": "store.policy", "detector": "components.detector", "odometry": "components.odometry",
    "loop_closure": "loop_closure.enabled", "vocabulary": "loop_closure.vocabulary",
}


def add_config_options(p: argparse.ArgumentParser) -> None:
    """``--config FILE`` and ``--set SECTION.KEY=VALUE`` on ``p``."""
    p.add_argument("--config", default=None, metavar="FILE",
                   help="settings file (TOML, YAML or JSON; e.g. a run's config.toml); see docs/configuration.md")
    p.add_argument("--set", dest="config_sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="one setting, over the file and DOPESLAM_SECTION__KEY variables (repeatable), "
                        "e.g. --set detector.stages=3 --set evidence.min_observations=3")


def flag_sets(args: argparse.Namespace) -> dict:
    """``{config key: value}`` of the short-form flags given on the command line (unset ones are
    None, or False for on/off switches, and set nothing)."""
    out = {}
    for dest, key in FLAG_KEYS.items():
        value = getattr(args, dest, None)
        if value is None or (value is False and key == "loop_closure.enabled"):
            continue
        out[key] = value
    return out


def config_from_args(args: argparse.Namespace, model=RunConfig, environ=None):
    """The resolved config of a parsed command line (``--config``, the environment, ``--set``, then
    the short-form flags). Raises :class:`stack.config.ConfigError`."""
    config = resolve_config(getattr(args, "config", None), list(getattr(args, "config_sets", []) or []),
                            environ, model)
    flags = {k: v for k, v in flag_sets(args).items() if k.split(".")[0] in model.model_fields}
    if flags:
        from stack.config import apply_sets

        config = apply_sets(config, flags, source=lambda k: f"--{_flag_name(k)}")
    return config


def _flag_name(key: str) -> str:
    dest = next(d for d, k in FLAG_KEYS.items() if k == key)
    return {"input_mode": "input"}.get(dest, dest).replace("_", "-")


def config_error(command: str, exc: ConfigError) -> int:
    """Print a config error as one line on stderr; the exit status for it (2)."""
    print(f"dopeslam {command}: {exc}", file=sys.stderr)
    return 2
