"""The ``dopeslam`` command line. Each sub-command lives in its own module under
``testbed/commands/`` and exposes ``register(subparsers)``; the module list below
is the single registry. Building the parser imports no simulator, network or odometry:
each command imports what it needs when it runs."""
from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import logging
import os
import sys
from pathlib import Path

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
    "testbed.commands.sweep",
]


DESCRIPTION = """\
A simulated Clearpath Jackal (PyBullet: RealSense D435i colour and depth, 32-beam Velodyne) drives
through scripted scenarios while the DOPESLAM stack under test (KISS-ICP LiDAR odometry, DOPE 6-DoF
object poses, false-positive reduction, fusion into a persistent object map) runs on its sensors;
every result is scored against the simulator's ground truth. The same stack runs on ROS 1 and
ROS 2 bags (replay), with or without ground truth.

Start with `dopeslam run` (a scored episode of the default scenario) and `dopeslam COMMAND --help`."""

EPILOG = "Progress bars go to stderr when it is a terminal (--quiet turns them off); results go to stdout."


# what an unset (None) option means where its help does not say
NONE_MEANS = {"seed": "the scenario's", "duration": "the scenario's", "light": "the scenario's"}
_NO_HELP = "\u200b"  # stands for "no help text" (argparse drops blank help, and its default with it)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's help ends with its default, unless the help already says it."""

    def _get_help_string(self, action):
        text = (action.help or "").replace(_NO_HELP, "").strip()
        if action.default is argparse.SUPPRESS or "%(default)" in text or "default" in text.lower():
            return text
        if not action.option_strings and action.nargs not in ("?", "*"):
            return text  # a required positional has no default
        if action.nargs == 0 and action.default is False:
            shown = "off"
        elif action.default is None:
            shown = NONE_MEANS.get(action.dest, "none")
        elif action.default == []:
            shown = "none"
        else:
            shown = "%(default)s"
        return f"{text} (default: {shown})" if text else f"(default: {shown})"


class _RawDescription(HelpFormatter, argparse.RawDescriptionHelpFormatter):
    """The top level: the description's paragraphs as written."""


class _SubCommands(argparse._SubParsersAction):
    """Sub-commands get the command's one-line help as their description too."""

    def add_parser(self, name, **kwargs):
        if "help" in kwargs and "description" not in kwargs:
            kwargs["description"] = kwargs["help"]
        return super().add_parser(name, **kwargs)


class CommandParser(argparse.ArgumentParser):
    """The parser of ``dopeslam`` and each sub-command: defaults shown; ``-q/--quiet`` on every command."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)
        self.register("action", "parsers", _SubCommands)
        if kwargs.get("add_help", True) and kwargs.get("prog") != "dopeslam":
            # SUPPRESS: given after the command it sets args.quiet; absent, the top level's value stays
            self.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                              help="no progress bars (they go to stderr, and only when it is a terminal)")

    def add_argument(self, *args, **kwargs):
        if kwargs.get("help") is None and args and str(args[0]).startswith("-"):
            kwargs["help"] = _NO_HELP  # argparse shows no help line (so no default) for an option without help
        return super().add_argument(*args, **kwargs)


class _Version(argparse.Action):
    """``--version``: the installed package's version (read only when asked)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"dopeslam {package_version()}")
        parser.exit()


def package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("dopeslam-testbed")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed: pip install -e .)"


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="dopeslam", description=DESCRIPTION, epilog=EPILOG, formatter_class=_RawDescription)
    parser.add_argument("--version", action=_Version, help="print the version and exit")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars (they go to stderr, and only when it is a terminal)")
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


@contextlib.contextmanager
def c_stdout_to_stderr():
    """While a command runs, file descriptor 1 (where C libraries such as PyBullet print their
    banners) goes to stderr; Python's ``print`` still reaches the real stdout. Off when stdout is
    not descriptor 1 (e.g. captured)."""
    try:
        if sys.stdout.fileno() != 1:
            raise ValueError
    except (AttributeError, OSError, ValueError):
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    old = sys.stdout
    sys.stdout = os.fdopen(saved, "w", buffering=1 if getattr(old, "line_buffering", False) else -1,
                           encoding=old.encoding, errors=old.errors)
    try:
        yield
    finally:
        ours, sys.stdout = sys.stdout, old
        os.dup2(saved, 1)
        ours.close()  # flushed first; closed even where the flush fails (a reader gone: BrokenPipeError)


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


# commands whose --out names a file (every other command's --out is a folder)
FILE_OUT_COMMANDS = {"config", "score", "dope-export", "dope-eval", "calibrate-fpr", "calibrate-int8"}


def check_output_args(args) -> None:
    """Every output a command was asked to write can be made where it was asked for (no file where
    a folder goes, no folder where a file goes, a writable folder above it), checked before any work
    starts: a bad ``--out`` costs a line, not an episode."""
    from testbed.io import check_output_path

    given = vars(args)
    outputs = [("out", "--out", "file" if args.command in FILE_OUT_COMMANDS else "folder"),
               ("junit", "--junit", "file"), ("view_save", "--view-save", "file"), ("store", "--store", "file"),
               ("results_bag", "--results-bag", "bag")]
    if args.command == "record":
        outputs.append(("bag", "--bag", "bag"))
    if given.get("update_baseline"):
        outputs.append(("baseline", "--baseline", "folder"))
    for attr, option, kind in outputs:
        if given.get(attr):
            if kind == "bag":  # a ROS 1 bag is one NAME.bag file, a ROS 2 bag a folder
                kind = "file" if Path(given[attr]).suffix == ".bag" else "folder"
            check_output_path(given[attr], option, kind)
    from testbed.settings import ENV_CACHE, cache_dir

    if os.environ.get(ENV_CACHE):  # every episode writes its object textures there
        check_output_path(cache_dir("", create=False), f"environment variable {ENV_CACHE}:")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    from testbed import progress

    progress.configure(quiet=getattr(args, "quiet", False))
    from sim.child import reuse_freed_memory

    reuse_freed_memory()  # this process and the ones it starts: docs/speed.md, "Freed memory kept for reuse"
    try:
        check_scenario_args(args)
        check_output_args(args)
        if getattr(args, "ray_address", None):  # before any work: a wrong address would cost Ray's minutes of retries
            from testbed.matrix import check_ray_address

            check_ray_address(args.ray_address)
        if not getattr(args, "json", False):
            with c_stdout_to_stderr():
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
    except BrokenPipeError:  # stdout's reader has gone (``| head``): the outputs are written, the rest of
        # the printout goes nowhere, and the status is a shell's for a writer that SIGPIPE stopped
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's last flush, silent
        except (AttributeError, OSError, ValueError):
            pass
        return 141
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
