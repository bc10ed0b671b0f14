"""``dopeslam odometry [SCENARIO] --out DIR --seed N [--duration S] [--odometry NAME|MODULE:CLASS]``: the
odometry on an episode through the stack's pipeline, scored against ground truth (ATE, RPE, TUM files, a
top-down PNG), wheel odometry beside it. Settings: ``--config FILE`` / ``--set`` ([odometry],
[components] odometry, [loop_closure]; docs/configuration.md)."""
from __future__ import annotations

from testbed.commands.options import add_config_options, config_error, config_from_args

# what dopeslam odometry applies of the config; anything else changed from its default is refused
APPLIES = {"odometry", "components.odometry", "loop_closure", "run"}


def register(sub) -> None:
    from testbed.commands.run import add_odometry_option

    p = sub.add_parser("odometry", help="odometry on an episode, scored against ground truth")
    p.add_argument("scenario", nargs="?", default=None,
                   help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--out", default="out/odometry", help="output folder (default: out/odometry)")
    p.add_argument("--seed", type=int, default=None, help="episode seed (default: the scenario's)")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the scenario's)")
    add_odometry_option(p)
    add_config_options(p)
    p.add_argument("--no-wheel", action="store_true", help="do not score wheel odometry")
    p.add_argument("--loop-closure", action="store_true",
                   help="close loops (vocabulary tree over camera key frames, LiDAR verification, pose graph)")
    p.add_argument("--json", action="store_true", help="print the scores as JSON on stdout (logs on stderr)")
    p.set_defaults(func=run)


def run(args) -> int:
    import json
    import sys

    from stack.config import ConfigError, write_config
    from stack.interfaces import ImportPathError, odometry_factory
    from testbed.commands.options import refuse_unapplied
    from testbed.commands.run import check_loop_closure
    from testbed.odometry import run_odometry

    try:
        config = config_from_args(args)
        refuse_unapplied(config, APPLIES, "odometry")
    except ConfigError as e:
        return config_error("odometry", e)
    try:
        odometry_factory(config.components.odometry)
    except ImportPathError as e:
        print(f"dopeslam odometry: --{e}", file=sys.stderr)
        return 2
    lc = config.loop_closure
    bad = check_loop_closure(lc.enabled, "odometry")
    if bad is not None:
        return bad
    r = config.run
    try:
        report = run_odometry(r.scenario, r.seed, args.out, r.duration, wheel=not args.no_wheel,
                              config=config.odometry, loop_closure=lc.enabled, odometry=config.components.odometry,
                              loop_closure_config=lc)
    except ImportPathError as e:  # the odometry's constructor failed
        print(f"dopeslam odometry: --{e}", file=sys.stderr)
        return 2
    write_config(config, f"{args.out}/config.toml")
    keys = ("scenario", "seed", "scans", "odometry_hz", "path_length_m", "ate_rmse_m", "ate_rmse_umeyama_m",
            "rpe_trans_pct", "rpe_rot_deg_per_m")
    keys += ("ate_rmse_odometry_only_m", "loop_closures", "loop_candidates_rejected", "false_loop_closures")
    brief = {k: report[k] for k in keys if k in report}
    if "wheel_odometry" in report:
        brief["wheel_odometry"] = {k: report["wheel_odometry"][k] for k in
                                   ("ate_rmse_m", "ate_rmse_umeyama_m", "rpe_trans_pct", "rpe_rot_deg_per_m")}
    args.json_result = brief  # --json (testbed/cli.py)
    print(json.dumps(brief, indent=2))
    print(f"wrote {args.out}/odometry.json, config.toml, estimate_tum.txt, groundtruth_tum.txt, odometry_topdown.png")
    return 0
