"""Soak: one long episode through the stack's pipeline (KISS-ICP odometry, the ground-truth detector,
fusion, the object store), with the process's resident memory and the wall time per simulated
second sampled as it runs, and the process's CPU time per simulated second (what other jobs on the
cores change far less than the wall time). Both should stay flat: memory growth after the first minute
well under 5 %, step time within noise.

    python benchmarks/bench_soak.py [SCENARIO] [--duration 1800] [--seed 0] [--every 10] [--json FILE]

It prints one row per ``--every`` simulated seconds (sim time, wall time, RSS MB, wall and CPU s per
sim s) and a summary line: RSS growth after the first minute and the step time (wall and CPU) of the
last quarter against the second.
"""
from __future__ import annotations

import argparse
import os
import resource
import time
from pathlib import Path


def rss_mb() -> float:
    """Resident set size now (Linux /proc), in MB."""
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * resource.getpagesize() / 1e6


def soak(scenario=None, duration: float = 1800.0, seed: int = 0, every: float = 10.0) -> dict:
    from sim.episode import Episode
    from sim.objects import load_catalog
    from stack.lidar_slam import LidarOdometry
    from stack.messages import CameraFrame
    from stack.pipeline import DopeSlam
    from testbed.oracle_detector import OracleDetector

    dims = {c: s.dims for c, s in load_catalog().items()}
    rows = []
    with Episode(scenario, seed=seed, duration=duration) as ep:
        detector = OracleDetector()
        detector.bind_episode(ep)
        pipe = DopeSlam(LidarOdometry(ep.T_base_velodyne), detector, ep.T_base_camera, dims, "robust-mean")
        wall0 = time.perf_counter()
        next_t, last_wall, last_t, last_cpu = every, wall0, 0.0, time.process_time()
        for msg in ep.frames():
            if isinstance(msg, CameraFrame):
                pipe.on_image(msg)
            else:
                pipe.on_message(msg)
            if msg.stamp >= next_t:
                now, cpu = time.perf_counter(), time.process_time()
                rows.append({"sim_s": round(msg.stamp, 1), "wall_s": round(now - wall0, 1), "rss_mb": round(rss_mb(), 1),
                             "wall_per_sim_s": round((now - last_wall) / max(msg.stamp - last_t, 1e-9), 3),
                             "cpu_per_sim_s": round((cpu - last_cpu) / max(msg.stamp - last_t, 1e-9), 3),
                             "map_objects": len(pipe.store)})
                print(" ".join(f"{k}={v}" for k, v in rows[-1].items()), flush=True)
                next_t += every
                last_wall, last_t, last_cpu = now, msg.stamp, cpu
        pipe.finish()
    after_minute = [r for r in rows if r["sim_s"] >= 60] or rows
    growth = (after_minute[-1]["rss_mb"] - after_minute[0]["rss_mb"]) / after_minute[0]["rss_mb"] if rows else None
    q = max(1, len(rows) // 4)

    def quarter_mean(key: str, part: list[dict]) -> float:
        return sum(r[key] for r in part) / len(part) if part else 0.0

    mid, last = rows[q:2 * q], rows[-q:]
    return {"scenario": ep.sc.name, "seed": seed, "duration": duration, "load_average": os.getloadavg()[0],
            "rss_growth_after_first_minute": growth, "step_second_quarter": quarter_mean("wall_per_sim_s", mid),
            "step_last_quarter": quarter_mean("wall_per_sim_s", last),
            "cpu_second_quarter": quarter_mean("cpu_per_sim_s", mid),
            "cpu_last_quarter": quarter_mean("cpu_per_sim_s", last), "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default=None)
    ap.add_argument("--duration", type=float, default=1800.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--every", type=float, default=10.0)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    r = soak(a.scenario, a.duration, a.seed, a.every)
    g = r["rss_growth_after_first_minute"]
    print(f"{r['scenario']} seed {r['seed']}, {r['duration']:.0f} s: RSS growth after the first minute "
          f"{'-' if g is None else f'{100 * g:.1f} %'}; wall s per sim s {r['step_second_quarter']:.2f} (2nd quarter) "
          f"-> {r['step_last_quarter']:.2f} (last quarter); CPU s per sim s {r['cpu_second_quarter']:.2f} -> "
          f"{r['cpu_last_quarter']:.2f}; load {r['load_average']:.1f}")
    if a.json:
        from stack.io import write_json

        write_json(Path(a.json), r)


if __name__ == "__main__":
    main()
