"""``dopeslam experiment NAME --out DIR``: the paper's experiments and the darkness sweep."""
from __future__ import annotations

import argparse
import importlib

from testbed.commands.options import add_config_options, config_error
from testbed.commands.run import add_dope_options

# name -> module under testbed.experiments with run(out_dir, **options) and table(result)
EXPERIMENTS = {
    "depth-grid": "testbed.experiments.depth_grid",      # paper experiment 1
    "precision": "testbed.experiments.precision",        # paper experiment 2
    "localization": "testbed.experiments.localization",  # paper experiment 3
    "darkness": "testbed.experiments.darkness",          # light sweep, RGB vs depth
    "faults": "testbed.experiments.faults",              # each sensor fault over its rate
}


def register(sub) -> None:
    p = sub.add_parser("experiment", help="run one of the paper's experiments (depth-grid, precision, localization) or the darkness sweep")
    p.add_argument("name", choices=sorted(EXPERIMENTS))
    p.add_argument("--out", default=None, help="output folder (default out/<name>)")
    p.add_argument("--scenario", default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--runs", type=int, default=None, help="precision: runs per configuration (paper: 5)")
    p.add_argument("--seconds", type=float, default=None, help="precision: seconds per run (paper: 60)")
    p.add_argument("--frames", type=int, default=None, help="depth-grid: frames per grid point")
    p.add_argument("--levels", type=_levels, default=None,
                   help="darkness: comma-separated light levels (default 1,0.5,0.25,0.1,0)")
    p.add_argument("--faults", type=_fault_sweep, default=None, metavar="NAME=R,R,...;NAME=...",
                   help="faults: the faults and rates to sweep (default: every fault, three rates; docs/faults.md)")
    p.add_argument("--jobs", type=int, default=1, help="darkness: episodes at once (local processes)")
    add_dope_options(p, defaults=False, unset=" (default: the config's when set there, else the experiment's own)")
    add_config_options(p)
    p.set_defaults(func=run)


def _fault_sweep(text: str) -> dict:
    from pydantic import ValidationError

    from testbed.experiments.faults import parse_faults_option

    try:
        return parse_faults_option(text)
    except ValidationError as e:
        raise argparse.ArgumentTypeError(f"{e.errors()[0]['loc'][0]}: {e.errors()[0]['msg']}") from None
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _levels(text: str) -> tuple[float, ...]:
    try:
        levels = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers in [0, 1], got {text!r}") from None
    if not levels or any(not 0.0 <= v <= 1.0 for v in levels):
        raise argparse.ArgumentTypeError(f"light levels must lie in [0, 1], got {text!r}")
    return levels


# the DOPE flags and their config keys: a flag beats the config, the config beats the experiment's own default
DOPE_FLAGS = {"input_mode": "detector.input", "stages": "detector.stages", "weights": "detector.weights"}


def experiment_config(args, module):
    """(the settings of ``--config``, ``DOPESLAM_SECTION__KEY`` and ``--set``, or None when they change
    nothing; ``{key: value}`` of those changed); a setting the experiment does not apply
    (``module.APPLIES``) raises ``ConfigError``."""
    from stack.config import changed_keys, resolve_config
    from testbed.commands.options import refuse_unapplied
    from testbed.settings import RunConfig

    config = resolve_config(args.config, list(args.config_sets), model=RunConfig)
    refuse_unapplied(config, module.APPLIES, f"experiment {args.name}")
    changed = changed_keys(config)
    return (config if changed else None), changed


def run(args) -> int:
    import inspect

    from stack.config import ConfigError

    module = importlib.import_module(EXPERIMENTS[args.name])
    out = args.out or f"out/{args.name}"
    try:
        config, changed = experiment_config(args, module)
    except ConfigError as e:
        return config_error(f"experiment {args.name}", e)
    opts = {"scenario": args.scenario, "seed": args.seed, "duration": args.duration, "runs": args.runs,
            "seconds": args.seconds, "frames": args.frames, "stages": args.stages, "input_mode": args.input_mode,
            "weights": args.weights, "levels": args.levels, "faults": args.faults, "jobs": args.jobs,
            "config": config}
    for dest, key in DOPE_FLAGS.items():
        if opts[dest] is None and key in changed:
            opts[dest] = changed[key]
    accepted = inspect.signature(module.run).parameters
    result = module.run(out, **{k: v for k, v in opts.items() if k in accepted and v is not None})
    print(module.table(result))
    print(f"wrote {out}")
    return 0
