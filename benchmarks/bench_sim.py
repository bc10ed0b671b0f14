"""Simulator speed: real-time factor of the default scenario's driving phase and each sensor's cost.

Runs the default scenario (route pause removed, so the robot drives the whole time) for ``--duration``
simulated seconds each way: physics only, + LiDAR, + camera, every sensor at its default rate (RGB +
depth 640x480 at 10 Hz, the full 32 x 1808 sweep at 10 Hz, wheel odometry at 20 Hz), and every sensor
with the camera rendered in a second process (``Episode(render_worker=True)``).

Reported per simulated second: CPU seconds (every thread of the process: the EGL software rasteriser
has its own; for the worker run, main + worker, the worker's start-up excluded), and the real-time
factor that CPU time allows on two idle cores (one process: 1 / CPU, as if it all ran on one core;
render worker: 1 / the busier process). Wall time is measured too, but on a shared machine it says
more about the other jobs than about the simulator, so the load average is printed with it. The
all-sensor run is also timed per call (LiDAR scan, camera render, depth noise, colour noise).

    python benchmarks/bench_sim.py [--duration 15] [--cpus 0,1] [--json benchmarks/results/sim.json]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import sim.camera as camera
from sim.episode import Episode
from sim.scenario import load_scenario
from stack.messages import CameraFrame, LidarScan


SECTIONS = ("lidar_scan", "camera_render", "depth_noise", "color_noise")


def driving_scenario(name: str | None = None):
    """The scenario with its start pause removed: every simulated second is driving."""
    sc = load_scenario(name)
    return sc.model_copy(update={"route": sc.route.model_copy(update={"start_pause": 0.0})})


class Timer:
    """Accumulates wall and CPU time of wrapped calls."""

    def __init__(self):
        self.calls = 0
        self.wall = 0.0
        self.cpu = 0.0
        self.thread_cpu = 0.0

    def wrap(self, fn):
        def timed(*args, **kwargs):
            w0, c0, t0 = time.perf_counter(), time.process_time(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.wall += time.perf_counter() - w0
                self.cpu += time.process_time() - c0
                self.thread_cpu += time.thread_time() - t0
                self.calls += 1
        return timed

    def per_call_ms(self) -> tuple[float, float, float]:
        n = max(self.calls, 1)
        return 1000 * self.wall / n, 1000 * self.cpu / n, 1000 * self.thread_cpu / n


def run_variant(sc, duration: float, camera_on: bool, lidar_on: bool, worker: bool = False,
                breakdown: bool = False) -> dict:
    children0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    ep = Episode(sc, seed=0, duration=duration, camera=camera_on, lidar=lidar_on, render_worker=worker)
    timers = {}
    originals = {}
    if breakdown:
        timers = {k: Timer() for k in SECTIONS}
        ep._lidar_scan = timers["lidar_scan"].wrap(ep._lidar_scan)
        for name, key in (("render_raw", "camera_render"), ("apply_depth_noise", "depth_noise"),
                          ("apply_color_noise", "color_noise")):
            originals[name] = getattr(camera, name)
            setattr(camera, name, timers[key].wrap(originals[name]))
    counts = {"camera": 0, "lidar": 0}
    worker_cpu = []  # the render worker's CPU time as of each frame
    try:
        w0, c0 = time.perf_counter(), time.process_time()
        for msg in ep.frames():
            if isinstance(msg, CameraFrame):
                counts["camera"] += 1
                if ep._render_workers:
                    worker_cpu.append(sum(w.worker_cpu_seconds for w in ep._render_workers))
            elif isinstance(msg, LidarScan):
                counts["lidar"] += 1
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    finally:
        for name, fn in originals.items():
            setattr(camera, name, fn)
        ep.close()
    sim_s = ep.sim_seconds
    out = {"sim_seconds": sim_s, "wall_seconds": wall, "main_cpu_per_sim_s": cpu / sim_s,
           "wall_per_sim_s": wall / sim_s, "real_time_factor": sim_s / wall,
           "camera_frames": counts["camera"], "lidar_scans": counts["lidar"]}
    if worker_cpu:
        # the worker's CPU per frame, from its first to its last frame (its start-up excluded)
        per_frame = (worker_cpu[-1] - worker_cpu[0]) / max(len(worker_cpu) - 1, 1)
        out["worker_cpu_per_sim_s"] = per_frame * counts["camera"] / sim_s
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        out["worker_total_cpu_seconds"] = (children.ru_utime + children.ru_stime
                                           - children0.ru_utime - children0.ru_stime)
        # two processes on two cores: the busier one sets the pace
        out["cpu_per_sim_s"] = out["main_cpu_per_sim_s"] + out["worker_cpu_per_sim_s"]
        out["idle_2core_rtf_estimate"] = 1.0 / max(out["main_cpu_per_sim_s"], out["worker_cpu_per_sim_s"])
    else:
        out["cpu_per_sim_s"] = out["main_cpu_per_sim_s"]
        out["idle_2core_rtf_estimate"] = 1.0 / out["cpu_per_sim_s"]  # as if one thread (the rasteriser has two)
    for k, t in timers.items():
        out[f"{k}_ms"], out[f"{k}_cpu_ms"], out[f"{k}_thread_cpu_ms"] = t.per_call_ms()
        out[f"{k}_calls"] = t.calls
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=None, help="bundled name or TOML path (default: the default scenario)")
    ap.add_argument("--duration", type=float, default=15.0, help="simulated seconds per variant")
    ap.add_argument("--cpus", default=None, help="pin to these CPUs, e.g. 0,1 (as taskset would)")
    ap.add_argument("--json", default=None, help="also write the results here")
    args = ap.parse_args(argv)
    if args.cpus:
        os.sched_setaffinity(0, {int(c) for c in args.cpus.split(",")})
    cpus = sorted(os.sched_getaffinity(0))
    load0 = os.getloadavg()
    sc = driving_scenario(args.scenario)
    s = sc.sensors
    print(f"bench_sim: scenario {sc.name} (driving phase), {args.duration:g} s simulated per run; "
          f"camera {s.camera_width}x{s.camera_height} @ {s.camera_rate:g} Hz, LiDAR 32 x {s.lidar_azimuth_steps} "
          f"@ {s.lidar_rate:g} Hz, physics {sc.physics_hz:g} Hz")
    print(f"CPUs usable: {len(cpus)} {cpus}; load average before: {load0[0]:.2f} (1 min) on {os.cpu_count()} CPUs")
    variants = [("physics only", False, False, False), ("physics + lidar", False, True, False),
                ("physics + camera", True, False, False), ("all sensors", True, True, False),
                ("all sensors, render worker", True, True, True)]
    results = {}
    for label, cam, lid, worker in variants:
        results[label] = run_variant(sc, args.duration, cam, lid, worker, breakdown=(label == "all sensors"))
        print(f"  ran {label}: {results[label]['wall_seconds']:.1f} s wall", file=sys.stderr)
    load1 = os.getloadavg()
    base = results["physics only"]
    print()
    print("| run | CPU s / sim s | sensor cost, CPU s / sim s | real-time factor from CPU time (idle 2 cores) "
          "| wall s / sim s, measured | real-time factor, measured |")
    print("|---|---:|---:|---:|---:|---:|")
    for label, *_ in variants:
        r = results[label]
        cost = "" if label == "physics only" else f"{r['cpu_per_sim_s'] - base['cpu_per_sim_s']:+.3f}"
        cpu = f"{r['cpu_per_sim_s']:.3f}"
        if "worker_cpu_per_sim_s" in r:
            cpu += f" ({r['main_cpu_per_sim_s']:.3f} main + {r['worker_cpu_per_sim_s']:.3f} worker)"
        print(f"| {label} | {cpu} | {cost} | {r['idle_2core_rtf_estimate']:.2f}x | {r['wall_per_sim_s']:.3f} "
              f"| {r['real_time_factor']:.2f}x |")
    a = results["all sensors"]
    print()
    print("| per call (all-sensor run) | calls | wall ms | CPU ms (process) | CPU ms (this thread) | wall s / sim s |")
    print("|---|---:|---:|---:|---:|---:|")
    for k in SECTIONS:
        print(f"| {k.replace('_', ' ')} | {a[k + '_calls']} | {a[k + '_ms']:.1f} | {a[k + '_cpu_ms']:.1f} | "
              f"{a[k + '_thread_cpu_ms']:.1f} | "
              f"{a[k + '_calls'] * a[k + '_ms'] / 1000 / a['sim_seconds']:.3f} |")
    print()
    w = results["all sensors, render worker"]
    for label, r in (("all sensors, one process", a), ("all sensors, render worker", w)):
        verdict = "meets" if r["real_time_factor"] >= 1.0 else "misses"
        print(f"{label}: measured {r['real_time_factor']:.2f}x real time ({verdict} the 1.0x target at this load); "
              f"from CPU time {r['idle_2core_rtf_estimate']:.2f}x on two idle cores")
    print(f"load average after: {load1[0]:.2f}")
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps({"duration": args.duration, "cpus": cpus, "load_before": load0,
                                   "load_after": load1, "results": results}, indent=2))
        os.replace(tmp, path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
