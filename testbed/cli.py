"""The ``dopeslam`` command line. Each sub-command lives in its own module under
``testbed/commands/`` and exposes ``register(subparsers)``; the module list below
is the single registry."""
from __future__ import annotations

import argparse
import errno
import importlib
import logging
import sys

from stack.errors import DopeSlamError

# the machine, not the program: a full disk, a read-only or forbidden folder
_ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}

COMMAND_MODULES = [
    "testbed.commands.scenes",
    "testbed.commands.simulate",
    "testbed.commands.odometry",
    "testbed.commands.dope",
    "testbed.commands.run",
    "testbed.commands.config",
    "testbed.commands.experiments",
    "testbed.commands.bags",
    "testbed.commands.policy",
    "testbed.commands.topomap",
    "testbed.commands.loops",
    "testbed.commands.test",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dopeslam", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a command module not written yet
            if exc.name == name:
                continue
            raise
        module.register(sub)
    return parser


# commands whose SCENARIO, --seed, --duration and --light are an episode's: checked before any work starts
SCENARIO_COMMANDS = {"run", "simulate", "odometry", "record", "navigate", "compare", "loop-closure", "loop-eval"}


def check_scenario_args(args) -> None:
    """The scenario named on the command line loaded (ScenarioError: one line) and the overrides
    validated by the scenario's own model (``--light 5``, ``--duration nan``, ``--seed -1``)."""
    if args.command not in SCENARIO_COMMANDS or "scenario" not in vars(args):
        return
    from sim.scenario import load_scenario, with_overrides

    scenario = args.scenario
    if isinstance(scenario, (list, tuple)):
        scenario = scenario[0] if scenario else None
    with_overrides(load_scenario(scenario), seed=getattr(args, "seed", None),
                   duration=getattr(args, "duration", None), light=getattr(args, "light", None))


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        check_scenario_args(args)
        if not getattr(args, "json", False):
            return int(args.func(args) or 0)
        # --json: only JSON on stdout; what the command prints (and the renderer's chatter) goes to stderr.
        # A command that supports it leaves its result in args.json_result.
        from testbed.testing.jsonout import stdout_to_stderr

        with stdout_to_stderr() as emit:
            rc = int(args.func(args) or 0)
            if getattr(args, "json_result", None) is not None:
                emit(args.json_result)
        return rc
    except KeyboardInterrupt:
        return 130
    except DopeSlamError as exc:  # what the user gave is wrong: one line (file, field, expected), no traceback
        print(f"dopeslam {args.command}: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.errno not in _ENVIRONMENT_ERRNOS:
            raise
        print(f"dopeslam {args.command}: {exc.strerror}: {exc.filename or ''}; no output was left half-written",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
