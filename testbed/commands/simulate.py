"""``dopeslam simulate [SCENARIO] --out DIR --seed N [--duration S]``."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("simulate", help="run an episode with all sensors and write samples, ground truth, a top-down PNG")
    p.add_argument("scenario", nargs="?", default=None, help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--out", default="out/simulate")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--duration", type=float, default=None)
    p.set_defaults(func=run)


def run(args) -> int:
    import json

    from testbed.simulate import run_simulation

    summary = run_simulation(args.scenario, args.out, args.seed, args.duration)
    print(json.dumps(summary, indent=2))
    return 0
