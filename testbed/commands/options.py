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

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where used: building the parser stays light
    from stack.config import ConfigError

# argparse destination -> config key, for the flags that are short forms of --set
FLAG_KEYS = {
    "scenario": "run.scenario", "seed": "run.seed", "light": "run.light", "duration": "run.duration",
    "profile": "run.profile", "lidar": "run.lidar",
    "input_mode": "detector.input", "stages": "detector.stages", "fpr": "detector.fpr",
    "weights": "detector.weights", "dope_every": "detector.every",
    "policy": "store.policy", "detector": "components.detector", "odometry": "components.odometry",
    "loop_closure": "loop_closure.enabled", "vocabulary": "loop_closure.vocabulary", "retire": "retire.enabled",
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


def config_from_args(args: argparse.Namespace, model=None, environ=None):
    """The resolved config of a parsed command line (``--config``, the environment, ``--set``, then
    the short-form flags); ``model`` defaults to :class:`testbed.settings.RunConfig`. Raises
    :class:`stack.config.ConfigError`."""
    from stack.config import resolve_config

    if model is None:
        from testbed.settings import RunConfig

        model = RunConfig
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


# what dopeslam replay applies of the config (the rest, changed from its default, is refused; [run] is
# the simulator's and is ignored)
REPLAY_APPLIES = {"detector", "components", "odometry", "store.policy", "loop_closure.enabled",
                  "loop_closure.vocabulary", "run"}


def refuse_unapplied(config, applied: set[str], command: str) -> None:
    """A setting changed from its default in a section (or key) the command does not apply is an
    error, never silently ignored. ``applied``: sections (``detector``) and keys (``store.policy``)
    the command honours."""
    from stack.config import ConfigError

    default = type(config)()
    for section in type(config).model_fields:
        if section in applied:
            continue
        have, want = getattr(config, section).model_dump(), getattr(default, section).model_dump()
        for key in have:
            if have[key] != want[key] and f"{section}.{key}" not in applied:
                raise ConfigError(f"key '{section}.{key}': dopeslam {command} does not apply it; "
                                  f"it applies {', '.join(sorted(applied))}")


def finish_outputs(config, out_dir, report: dict, detector, seed=None, scenario=None) -> None:
    """OUT/config.toml (the resolved config) and report.json's ``provenance``, for a job whose
    runner does not write them itself."""
    from pathlib import Path

    from stack.config import write_config
    from testbed.io import write_json
    from testbed.provenance import detector_files, provenance

    out = Path(out_dir)
    write_config(config, out / "config.toml")
    w, t = detector_files(detector)
    report["provenance"] = provenance(seed, scenario, w, t)
    write_json(out / "report.json", {k: v for k, v in report.items() if not k.startswith("_")})
