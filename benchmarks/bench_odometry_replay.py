"""Odometry-only replay of a bag against KISS-ICP's own command on the same bag.

Records a bag of the default scenario's drive (or takes ``--bag``), then runs, in turn and
``--repeats`` times each (paired, so a busy moment hits both):

- ``kiss_icp_pipeline --config K --topic /velodyne_points BAG`` with the stack's KISS-ICP settings
  (``stack.lidar_slam.LidarOdometryConfig.to_kiss``; KISS-ICP's default 1 m voxels are for outdoor
  ranges), no visualiser;
- ``dopeslam replay BAG --odometry-only``: the stack's odometry (KISS-ICP plus its floor fit) over the
  LiDAR topic, with the outputs a user gets (trajectory, LiDAR map, map.png, results bag).

Each in a fresh process, timed by wall clock and by the children's CPU time
(``resource.getrusage(RUSAGE_CHILDREN)``); start-up (imports) is included in both. The target: the
replay at most 1.5x KISS-ICP's wall time.

    python benchmarks/bench_odometry_replay.py [--duration 20] [--repeats 2] [--bag BAG] [--keep DIR]
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _timed(cmd: list[str], cwd: Path, env: dict) -> tuple[float, float]:
    """(wall s, CPU s) of one child process; raises on a non-zero exit with its output's tail."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:3])}... exited {proc.returncode}: {(proc.stdout + proc.stderr)[-1500:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of the default scenario to record")
    ap.add_argument("--repeats", type=int, default=2, help="paired runs of each command")
    ap.add_argument("--bag", default=None, help="an existing bag (LiDAR on /velodyne_points) instead of recording")
    ap.add_argument("--keep", default=None, help="keep the bag and the outputs in this folder")
    args = ap.parse_args(argv)

    from stack.lidar_slam import LidarOdometryConfig
    from testbed.bags.topics import LIDAR

    work = Path(args.keep or tempfile.mkdtemp(prefix="bench_odo_replay_")).resolve()
    work.mkdir(parents=True, exist_ok=True)
    bag = Path(args.bag).resolve() if args.bag else work / "bag"
    if not args.bag and not bag.exists():
        from testbed.record import record_episode

        print(f"recording {args.duration:.0f} s of the default scenario to {bag} ...", file=sys.stderr)
        record_episode(None, bag, seed=0, duration=args.duration)
    from kiss_icp.config import write_config

    kiss = LidarOdometryConfig(floor_constraint=False).to_kiss()
    kiss.out_dir = str(work / "kiss_out")
    write_config(kiss, str(work / "kiss.yaml"))
    exe_dir = Path(sys.executable).parent
    kiss_cmd = [shutil.which("kiss_icp_pipeline") or str(exe_dir / "kiss_icp_pipeline"), "--config",
                str(work / "kiss.yaml"), "--topic", LIDAR, str(bag)]
    ours_cmd = [shutil.which("dopeslam") or str(exe_dir / "dopeslam"), "-q", "replay", str(bag), "--odometry-only",
                "--force", "--out", str(work / "replay_out")]
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    rows = {"kiss_icp_pipeline": [], "dopeslam replay --odometry-only": []}
    for i in range(args.repeats):
        for name, cmd in (("kiss_icp_pipeline", kiss_cmd), ("dopeslam replay --odometry-only", ours_cmd)):
            rows[name].append(_timed(cmd, work, env))
            print(f"repeat {i + 1}/{args.repeats}: {name}: wall {rows[name][-1][0]:.1f} s, "
                  f"CPU {rows[name][-1][1]:.1f} s", file=sys.stderr)
    k_wall = statistics.median(w for w, _ in rows["kiss_icp_pipeline"])
    k_cpu = statistics.median(c for _, c in rows["kiss_icp_pipeline"])
    from testbed.bags.writer import bag_size

    print(f"\nbag: {bag} ({bag_size(bag) / 1e6:.0f} MB); "
          f"load average at the end: {' '.join(os.getloadavg().__repr__().strip('()').split(', '))}\n")
    print("| command | wall s (median) | CPU s (median) | wall / kiss_icp_pipeline (target <= 1.5) | CPU / kiss_icp_pipeline |")
    print("|---|---:|---:|---:|---:|")
    for name, r in rows.items():
        wall, cpu = statistics.median(w for w, _ in r), statistics.median(c for _, c in r)
        print(f"| {name} | {wall:.1f} | {cpu:.1f} | {wall / k_wall:.2f} | {cpu / k_cpu:.2f} |")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
