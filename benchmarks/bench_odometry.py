"""LiDAR odometry speed: scans per second of ``stack.lidar_slam.LidarOdometry`` on full sweeps.

Simulates ``--duration`` seconds of the default scenario's drive (start pause removed; the full
32 x 1808 sweep at 10 Hz), keeps the scans in memory, then times ``process`` on every scan for a few
configurations. The target is 20 scans/s (twice the sensor rate) on the two cores of the dev machine.

Reported per configuration: wall ms per scan (mean, 95th percentile), CPU ms per scan (all threads of
the process), scans/s by wall clock, and ATE / RPE against ground truth so that a faster setting is
not read without its accuracy. On a shared machine wall time says as much about the other jobs as
about the odometry; the load average is printed with it. KISS-ICP's thread count is fixed for the
process at the first odometry built (a TBB global), so ``--threads`` applies to the whole run.

    python benchmarks/bench_odometry.py [--duration 20] [--threads 0] [--scenario NAME]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from stack import metrics
from stack.lidar_slam import LidarOdometry, LidarOdometryConfig


def simulate(scenario: str | None, duration: float, seed: int):
    from sim.episode import Episode
    from sim.scenario import load_scenario
    from stack.messages import LidarScan

    sc = load_scenario(scenario)
    sc = sc.model_copy(update={"route": sc.route.model_copy(update={"start_pause": 0.0})})
    with Episode(sc, seed=seed, duration=duration, camera=False) as ep:
        scans = [m for m in ep.frames() if isinstance(m, LidarScan)]
        return sc.name, scans, ep.T_base_velodyne, ep.T_world_base_at


def bench(scans, T_base_velodyne, gt_at, config: LidarOdometryConfig) -> dict:
    odo = LidarOdometry(T_base_velodyne, config)
    wall, cpu = [], []
    for s in scans:
        w0, c0 = time.perf_counter(), time.process_time()
        odo.process(s)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    stamps, T_map_base = odo.trajectory()
    gt = gt_at(stamps)
    est = gt[0] @ T_map_base
    wall_ms, cpu_ms = 1e3 * np.array(wall), 1e3 * np.array(cpu)
    return {"wall_ms": wall_ms.mean(), "wall_p95_ms": np.percentile(wall_ms, 95), "cpu_ms": cpu_ms.mean(),
            "hz": 1e3 / wall_ms.mean(), "ate_cm": 100 * metrics.ate_rmse(est, gt),
            "rpe_pct": metrics.rpe(est, gt, 1.0).trans_pct}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=None)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0, help="KISS-ICP threads (0: all cores)")
    args = ap.parse_args()

    t0 = time.perf_counter()
    name, scans, E, gt_at = simulate(args.scenario, args.duration, args.seed)
    points = np.mean([len(s.points) for s in scans])
    print(f"{name}: {len(scans)} scans of {points:.0f} points simulated in {time.perf_counter() - t0:.0f} s; "
          f"{os.cpu_count()} cores, KISS-ICP threads {args.threads or 'all'}")

    default = LidarOdometryConfig(threads=args.threads)
    bench(scans[:20], E, gt_at, default)  # warm up: thread pool, allocator, caches
    configs = [
        (f"default ({default.voxel_size_m:g} m voxel)", default),
        ("no deskew", default.model_copy(update={"deskew": False})),
        ("no floor levelling", default.model_copy(update={"floor_constraint": False})),
        ("voxel 0.15 m", default.model_copy(update={"voxel_size_m": 0.15})),
        ("voxel 0.25 m", default.model_copy(update={"voxel_size_m": 0.25})),
        ("voxel 0.35 m", default.model_copy(update={"voxel_size_m": 0.35})),
    ]
    header = (f"{'configuration':<24} {'wall ms':>8} {'p95 ms':>7} {'CPU ms':>7} {'scans/s':>8} {'ATE cm':>7} "
              f"{'RPE %':>6}  load")
    print(header)
    print("-" * len(header))
    for label, cfg in configs:
        r = bench(scans, E, gt_at, cfg)
        load = os.getloadavg()[0]
        print(f"{label:<24} {r['wall_ms']:8.1f} {r['wall_p95_ms']:7.1f} {r['cpu_ms']:7.1f} {r['hz']:8.1f} "
              f"{r['ate_cm']:7.2f} {r['rpe_pct']:6.2f}  {load:.1f}", flush=True)


if __name__ == "__main__":
    main()
