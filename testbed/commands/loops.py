"""``dopeslam loop-closure`` (odometry with and without loop closure on a scenario, no DOPE) and
``dopeslam loop-eval`` (place-recognition precision/recall and closure scoring)."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("loop-closure", help="LiDAR odometry with and without loop closure on a looping scenario")
    p.add_argument("scenario", nargs="?", default="office_loop")
    p.add_argument("--out", default="out/loop_closure")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--vocabulary", default=None, help="vocabulary .npz (default: built from the training scenarios)")
    p.add_argument("--proximity", choices=["fallback", "always", "never"], default=None,
                   help="LiDAR-proximity candidates (default: fallback, when retrieval has none)")
    p.set_defaults(func=_loop_closure)

    e = sub.add_parser("loop-eval", help="place-recognition retrieval precision/recall and loop-closure scores")
    e.add_argument("scenario", nargs="?", default=None, help="default: the loop-eval scenario (office_loop_twice)")
    e.add_argument("--out", default="out/loop_eval")
    e.add_argument("--seed", type=int, default=None)
    e.add_argument("--duration", type=float, default=None)
    e.add_argument("--vocabulary", default=None, help="a vocabulary .npz (default: trained on the first lap)")
    e.add_argument("--branching", type=int, default=10)
    e.add_argument("--depth", type=int, default=3)
    e.add_argument("--keep-key-frames", action="store_true", help="save (and reuse) OUT/key_frames.npz")
    e.set_defaults(func=_loop_eval)


def _loop_closure(args) -> int:
    from testbed import loop_closing

    argv = [args.scenario, "--out", args.out]
    for flag, v in (("--seed", args.seed), ("--duration", args.duration), ("--vocabulary", args.vocabulary),
                    ("--proximity", args.proximity)):
        if v is not None:
            argv += [flag, str(v)]
    return loop_closing.main(argv)


def _loop_eval(args) -> int:
    from testbed import loop_eval

    argv = [args.scenario or loop_eval.DEFAULT_SCENARIO, "--out", args.out,
            "--branching", str(args.branching), "--depth", str(args.depth)]
    for flag, v in (("--seed", args.seed), ("--duration", args.duration), ("--vocabulary", args.vocabulary)):
        if v is not None:
            argv += [flag, str(v)]
    if args.keep_key_frames:
        argv.append("--keep-key-frames")
    return loop_eval.main(argv)
