"""The cost of a sweep: one cell's cost, the throughput of local processes (``--jobs 1`` against
``--jobs 2``), Ray's per-task overhead on this machine, and the projected wall time of 1,000 default
episodes on N nodes of C cores.

Ray's overhead is the time per no-op task (submitted in a batch, results gathered) and per task
returning a report-sized result (50 KB), on a local Ray runtime with the machine's cores. The cells are
real `dopeslam run` episodes of ``--duration`` seconds through :func:`testbed.matrix.run_cells`.
Other busy processes on the cores slow every row: the load average is printed with the table.

    python benchmarks/bench_sweep.py [--duration S] [--cells N] [--tasks N] [--skip-cells]
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def ray_overhead(tasks: int) -> dict:
    import ray

    ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    try:
        @ray.remote(num_cpus=1)
        def noop(i):
            return i

        @ray.remote(num_cpus=1)
        def report_sized(i):
            return {"i": i, "blob": "x" * 50_000}

        ray.get([noop.remote(i) for i in range(os.cpu_count() * 2)])  # workers started
        t0 = time.perf_counter()
        ray.get([noop.remote(i) for i in range(tasks)])
        per_noop = (time.perf_counter() - t0) / tasks
        t0 = time.perf_counter()
        ray.get([report_sized.remote(i) for i in range(tasks)])
        per_report = (time.perf_counter() - t0) / tasks
        t0 = time.perf_counter()
        for i in range(min(tasks, 50)):
            ray.get(noop.remote(i))
        round_trip = (time.perf_counter() - t0) / min(tasks, 50)
    finally:
        ray.shutdown()
    return {"per_task_s": per_noop, "per_report_task_s": per_report, "round_trip_s": round_trip}


def cells_throughput(duration: float, n: int) -> dict:
    from testbed.matrix import Cell, run_cells

    out = {}
    for jobs in (1, 2):
        cells = [Cell("experiment3_columns", s, {"duration": duration}) for s in range(n)]
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            res = run_cells(cells, tmp, jobs=jobs, progress=False)
            wall = time.perf_counter() - t0
        ok = [r for r in res if r["status"] == "ok"]
        out[jobs] = {"wall_s": wall, "cells": len(ok), "cells_per_hour": 3600 * len(ok) / wall,
                     "cell_wall_s": sum(r["report"]["wall_seconds"] for r in ok) / max(1, len(ok)),
                     "sim_s": duration}
        print(f"--jobs {jobs}: {len(ok)} cells of {duration:.0f} s in {wall:.0f} s", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds per cell")
    ap.add_argument("--cells", type=int, default=4, help="cells per backend (seeds 0..N-1)")
    ap.add_argument("--tasks", type=int, default=200, help="Ray tasks per overhead measurement")
    ap.add_argument("--skip-cells", action="store_true", help="only Ray's overhead")
    args = ap.parse_args(argv)

    try:
        ov = ray_overhead(args.tasks)
    except ImportError:
        ov = None
        print("Ray is not installed (pip install -e '.[ray]'): no overhead row")
    th = None if args.skip_cells else cells_throughput(args.duration, args.cells)
    print(f"\nload average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}; {os.cpu_count()} cores")
    print("| measure | value |")
    print("|---|---:|")
    if ov:
        print(f"| Ray: no-op task, batched ({args.tasks}) | {1000 * ov['per_task_s']:.2f} ms |")
        print(f"| Ray: task returning 50 KB, batched | {1000 * ov['per_report_task_s']:.2f} ms |")
        print(f"| Ray: one task's submit-and-get round trip | {1000 * ov['round_trip_s']:.2f} ms |")
    if th:
        one, two = th[1], th[2]
        # one core's share of the --jobs 2 throughput: what each slot of a cluster does
        per_sim = 2 * two["wall_s"] / max(1, two["cells"]) / args.duration
        print(f"| cell of {args.duration:.0f} s, --jobs 1: wall per cell (process start included) | "
              f"{one['wall_s'] / one['cells']:.1f} s |")
        print(f"| ... of which the episode itself (report's wall_seconds) | {one['cell_wall_s']:.1f} s |")
        print(f"| throughput --jobs 2 / --jobs 1 | {two['cells_per_hour'] / one['cells_per_hour']:.2f}x |")
        cell60 = per_sim * 60
        print(f"| projected default 60 s cell per core (from --jobs 2, linear in sim time) | {cell60:.0f} s |")
        for nodes, cores in ((1, 2), (4, 16), (16, 32)):
            slots = nodes * cores
            overhead = (ov["per_report_task_s"] if ov else 0.0) * 1000 / slots
            t = math.ceil(1000 / slots) * cell60 + overhead
            print(f"| projected 1,000 default episodes on {nodes} node(s) x {cores} cores | {t / 3600:.1f} h |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
