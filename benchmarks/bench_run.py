"""The main job's speed: a whole ``dopeslam run`` episode (default scenario, RGB, 6 stages, FPR) against
the target of three times real time on two cores (the 60 s episode in at most 20 s), and where the time
goes.

Prints, per repeat: simulated seconds, wall seconds, wall / sim (the target is <= 0.33), the split of the
time (simulation incl. rendering, LiDAR odometry, DOPE incl. depth fit and FPR, fusion), the CPU
seconds per simulated second, the scores, and where KISS-ICP ran (a child process of its own where
some images go undetected, docs/speed.md). Other busy processes on the cores slow every row: note
the load average printed with the table.

    python benchmarks/bench_run.py [--scenario NAME] [--duration S] [--repeats N] [--stages 1-6] [--profile full|fast]
                                   [--set KEY=VALUE ...]

``--set`` takes any config key, e.g. ``--set detector.keyframe_m=0.1 --set detector.keyframe_deg=5``
(the keyframe gate). The CPU column counts the run's child processes too (the detector's and the
renderer's), as ``/usr/bin/time`` would.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=None, help="bundled name or TOML (default: the default scenario)")
    ap.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's, 60 s)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--stages", type=int, default=6)
    ap.add_argument("--profile", choices=["full", "fast"], default="full",
                    help="the run profile (fast: camera at half rate, no segmentation image; docs/speed.md)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config key for every repeat, e.g. detector.keyframe_m=0.1 (repeatable)")
    args = ap.parse_args(argv)

    from stack.config import ConfigError
    from testbed.run import run_episode
    from testbed.settings import RunConfig

    config = None
    if args.set:
        from stack.config import resolve_config

        try:
            config = resolve_config(sets=[f"detector.stages={args.stages}", *args.set], model=RunConfig)
        except ConfigError as e:
            print(f"bench_run: {e}", file=sys.stderr)
            return 2

    def cpu_seconds() -> float:  # this process and its finished children (detector, renderer)
        own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime

    rows = []
    for i in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            c0 = cpu_seconds()
            r = run_episode(args.scenario, out_dir=tmp, seed=0, stages=args.stages, duration=args.duration,
                            write_outputs=False, profile=args.profile, config=config)
            cpu = cpu_seconds() - c0
        split = r["time_split_s"]
        rows.append((i, r["sim_seconds"], r["wall_seconds"], split, cpu, r["labels_summary"], r["odometry_process"]))
        print(f"repeat {i + 1}/{args.repeats}: {r['wall_seconds']:.1f} s for {r['sim_seconds']:.0f} s", flush=True)
    print(f"\nload average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("| repeat | sim s | wall s | wall / sim (target <= 0.33) | simulation s | odometry s | DOPE s | fusion s "
          "| CPU s / sim s | labelled | false | mean error | KISS-ICP |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for i, sim, wall, split, cpu, ls, own_process in rows:
        err = "-" if ls["mean_error_m"] is None else f"{100 * ls['mean_error_m']:.1f} cm"
        print(f"| {i + 1} | {sim:.0f} | {wall:.1f} | {wall / sim:.2f} | {split['simulation']:.1f} | "
              f"{split['odometry']:.1f} | {split['dope']:.1f} | {split['fusion']:.1f} | {cpu / sim:.2f} | "
              f"{ls['labelled']}/{ls['objects']} | {ls['false_labels']} | {err} | "
              f"{'own process' if own_process else 'in the run'} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
