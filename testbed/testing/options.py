"""The options a test case (or the pytest fixture) gives one episode: `dopeslam run`'s flags by name,
checked before anything runs, and the one place they become a call of ``run_episode``."""
from __future__ import annotations

from pathlib import Path

from stack.errors import DopeSlamError

# name -> (type, check, what is expected)
RUN_OPTIONS = {
    "duration": (float, lambda v: 0 < v <= 3600, "seconds, > 0"),
    "light": (float, lambda v: 0 <= v <= 1, "a light level from 0 to 1"),
    "input": (str, lambda v: v in ("rgb", "depth"), "rgb or depth"),
    "stages": (int, lambda v: 1 <= v <= 6, "1-6"),
    "fpr": (bool, lambda v: True, "true or false"),
    "policy": (str, lambda v: bool(v), "a policy name or MODULE:FUNCTION"),
    "detector": (str, lambda v: ":" in v, "MODULE:CLASS"),
    "loop_closure": (bool, lambda v: True, "true or false"),
    "weights": (str, lambda v: bool(v), "a weights file"),
}
NAVIGATE_OPTIONS = {
    "object": (str, lambda v: bool(v), "an object's name or class in the scenario"),
    "max_seconds": (float, lambda v: v > 0, "seconds, > 0"),
    "wheels_only": (bool, lambda v: True, "true or false"),
}
JOBS = ("run", "navigate")


class OptionError(DopeSlamError, ValueError):
    """An option that cannot be used; the message names it and what was expected."""


def coerce(name: str, value, table: dict):
    typ, ok, what = table[name]
    given = value
    if isinstance(value, str) and typ is not str:  # from --set key=value
        low = value.strip().lower()
        try:
            value = {"true": True, "false": False}[low] if typ is bool else typ(value)
        except (KeyError, ValueError):
            raise OptionError(f"option '{name}': expected {what}, got {value!r}") from None
    if typ is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, typ) or (typ is not bool and isinstance(value, bool)) or not ok(value):
        raise OptionError(f"option '{name}': expected {what}, got {given!r}")
    return value


def check_setting(key: str, value):
    """A ``SECTION.KEY`` stack setting checked against the config (``stack.config``); its value as given."""
    from stack.config import ConfigError, apply_sets
    from testbed.settings import RunConfig

    try:
        apply_sets(RunConfig(), {key: value}, source=lambda k: f"option '{k}'")
    except ConfigError as e:
        raise OptionError(str(e)) from None
    return value


def check_options(options: dict) -> dict:
    """Validated copy of a case's options (``job`` = run | navigate, then that job's options)."""
    opts = dict(options)
    job = opts.pop("job", "run")
    if job not in JOBS:
        raise OptionError(f"option 'job': expected one of {', '.join(JOBS)}, got {job!r}")
    table = NAVIGATE_OPTIONS if job == "navigate" else RUN_OPTIONS
    out = {}
    for name, value in opts.items():
        if job == "run" and "." in name:  # a stack setting, SECTION.KEY (docs/configuration.md)
            out[name] = check_setting(name, value)
            continue
        if name not in table:
            raise OptionError(f"option '{name}': not an option of the {job} job; options: {', '.join(sorted(table))}")
        out[name] = coerce(name, value, table)
    if job == "navigate":
        if "object" not in out:
            raise OptionError("option 'object': the navigate job needs the object to drive to")
        out["job"] = "navigate"
    return out


def run_one(scenario: str, seed: int, options: dict, out_dir: str | Path) -> dict:
    """One episode with these options (already checked); returns its report (report.json or navigate.json)."""
    opts = check_options(options)
    if opts.get("job") == "navigate":
        from testbed.topomap.navigate import navigate

        return navigate(opts["object"], scenario, str(out_dir), seed, opts.get("max_seconds"),
                        gyro=not opts.get("wheels_only", False))
    try:
        from testbed.matrix import Cell, execute
    except ImportError:
        execute = None
    if execute is not None:  # the options resolved into the stack's config, as `dopeslam run` does
        from sim.scenario import DEFAULT_SCENARIO

        return execute(Cell(DEFAULT_SCENARIO if scenario is None else str(scenario), int(seed), opts), Path(out_dir))
    from stack.interfaces import load_detector, resolve_policy
    from testbed.run import run_episode

    policy = resolve_policy(opts.get("policy", "robust-mean"))
    detector = load_detector(opts["detector"]) if opts.get("detector") else None
    return run_episode(scenario, str(out_dir), seed, opts.get("light"), opts.get("input", "rgb"), opts.get("stages", 6),
                       opts.get("fpr", True), policy, opts.get("duration"), opts.get("weights"), detector=detector,
                       loop_closure=opts.get("loop_closure", False))
