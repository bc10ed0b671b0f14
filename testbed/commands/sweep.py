"""``dopeslam sweep SCENARIO_OR_SUITE... --seeds 0-99 [--grid KEY=V1,V2]... [--set KEY=VALUE]... [--out DIR]
[--jobs N | --ray | --ray-address ADDR] [--collect-files]``: many episodes, one row each (docs/scale.md)."""
from __future__ import annotations

import os


def register(sub) -> None:
    p = sub.add_parser("sweep", help="scenarios x seeds x grid values of any config key, in local processes or on "
                                     "a Ray cluster: results.csv, sweep.json, a plot per metric and grid key")
    p.add_argument("targets", nargs="+", metavar="SCENARIO_OR_SUITE",
                   help="bundled scenario names or TOML paths, or suites (bundled: mission, smoke)")
    p.add_argument("--seeds", default=None,
                   help="e.g. 0-99 or 0-9,20,31-35 (default: the suite's seeds, else the scenario's own seed)")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="a config key and its values, e.g. detector.stages=1,3,6, light=1,0.25,0 or input=rgb,depth "
                        "(repeatable: the cross product)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="a config key for every cell, e.g. duration=20")
    p.add_argument("--out", default="out/sweep", help="results.csv, rows.jsonl, sweep.json, plots and cells/ "
                                                      "(a rerun into the same folder skips finished cells)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="local processes, one cell each (torch single-threaded in each)")
    p.add_argument("--ray", action="store_true", help="run each cell as a task on a local Ray runtime")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="join an existing Ray cluster (e.g. 10.0.0.1:6379; `ray start --head` prints it)")
    p.add_argument("--collect-files", action="store_true",
                   help="with Ray: bring every cell's output folder back to OUT/cells/ (default: report.json only)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNGs")
    p.add_argument("--json", action="store_true", help="print sweep.json's content on stdout (logs on stderr)")
    p.set_defaults(func=run)


def run(args) -> int:
    import sys

    from testbed import progress
    from testbed.sweep import sweep

    summary = sweep(args.targets, args.out, seeds=args.seeds, grid=args.grid, sets=args.sets, jobs=args.jobs,
                    ray=args.ray, ray_address=args.ray_address, collect_files=args.collect_files,
                    progress=progress.enabled(),
                    plots=not args.no_plots)
    args.json_result = summary
    print(f"{summary['cells']} cells: {summary['ok']} ok, {summary['errors']} errors, {summary['resumed']} already "
          f"done; {summary['wall_seconds']:.0f} s on {summary['backend']}")
    print(f"wrote {args.out}/results.csv, sweep.json" + (", " + ", ".join(summary["plots"]) if summary["plots"] else ""),
          file=sys.stderr)
    return 0 if summary["errors"] == 0 else 1
