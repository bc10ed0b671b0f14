"""``dopeslam odometry [SCENARIO] --out DIR --seed N [--duration S]``: KISS-ICP LiDAR odometry on an
episode, scored against ground truth (ATE, RPE, TUM files, a top-down PNG), wheel odometry beside it."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("odometry", help="LiDAR odometry on an episode, scored against ground truth")
    p.add_argument("scenario", nargs="?", default=None,
                   help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--out", default="out/odometry", help="output folder (default: out/odometry)")
    p.add_argument("--seed", type=int, default=None, help="episode seed (default: the scenario's)")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the scenario's)")
    p.add_argument("--config", default=None, help="YAML file overriding the odometry settings (stack.lidar_slam)")
    p.add_argument("--no-wheel", action="store_true", help="do not score wheel odometry")
    p.add_argument("--loop-closure", action="store_true",
                   help="close loops (vocabulary tree over camera key frames, LiDAR verification, pose graph)")
    p.add_argument("--json", action="store_true", help="print the scores as JSON on stdout (logs on stderr)")
    p.set_defaults(func=run)


def run(args) -> int:
    import json

    from stack.lidar_slam import load_config
    from testbed.odometry import run_odometry

    config = load_config(args.config)
    report = run_odometry(args.scenario, args.seed, args.out, args.duration, wheel=not args.no_wheel, config=config,
                          loop_closure=args.loop_closure)
    keys = ("scenario", "seed", "scans", "odometry_hz", "path_length_m", "ate_rmse_m", "ate_rmse_umeyama_m",
            "rpe_trans_pct", "rpe_rot_deg_per_m")
    keys += ("ate_rmse_odometry_only_m", "loop_closures", "loop_candidates_rejected", "false_loop_closures")
    brief = {k: report[k] for k in keys if k in report}
    if "wheel_odometry" in report:
        brief["wheel_odometry"] = {k: report["wheel_odometry"][k] for k in
                                   ("ate_rmse_m", "ate_rmse_umeyama_m", "rpe_trans_pct", "rpe_rot_deg_per_m")}
    args.json_result = brief  # --json (testbed/cli.py)
    print(json.dumps(brief, indent=2))
    print(f"wrote {args.out}/odometry.json, estimate_tum.txt, groundtruth_tum.txt, odometry_topdown.png")
    return 0
