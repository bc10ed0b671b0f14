"""``dopeslam run [SCENARIO] --out DIR --seed N [--light L] [--input rgb|depth] [--stages 1-6] [--fpr/--no-fpr] [--policy NAME]``."""
from __future__ import annotations

import argparse


def add_dope_options(p: argparse.ArgumentParser, defaults: bool = True) -> None:
    """The options of every command that runs DOPE. ``defaults=False``: unset options are None, so the
    command (e.g. an experiment with the paper's own input) keeps its default."""
    p.add_argument("--input", dest="input_mode", choices=["rgb", "depth"], default="rgb" if defaults else None,
                   help="DOPE input image" + ("" if defaults else " (default: the experiment's own)"))
    p.add_argument("--stages", type=int, choices=range(1, 7), default=6 if defaults else None, metavar="1-6",
                   help="DOPE stages to run")
    p.add_argument("--fpr", action=argparse.BooleanOptionalAction, default=True, help="false-positive reduction")
    p.add_argument("--weights", default=None, help="weights file (default: the shipped ones for --input)")


def register(sub) -> None:
    p = sub.add_parser("run", help="the main job: a scored drive-through episode (report, labels.xlsx, map.png)")
    p.add_argument("scenario", nargs="?", default=None, help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--out", default="out/run")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--light", type=float, default=None, help="override the scenario's light level (0-1)")
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--policy", default="robust-mean", help="labelling policy: last, last-fpr, best-score, robust-mean, ...")
    p.add_argument("--loop-closure", action="store_true",
                   help="close loops (vocabulary tree + LiDAR verification + pose graph); labels move with them")
    add_dope_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from stack.object_store import POLICIES
    from testbed.run import print_summary, run_episode

    if args.policy not in POLICIES:
        raise SystemExit(f"--policy: expected one of {sorted(POLICIES)}, got {args.policy!r}")
    report = run_episode(args.scenario, args.out, args.seed, args.light, args.input_mode, args.stages, args.fpr,
                         args.policy, args.duration, args.weights, loop_closure=args.loop_closure)
    print_summary(report)
    print(f"wrote {args.out}/report.json, labels.xlsx, map.png, estimate_tum.txt, groundtruth_tum.txt")
    return 0
