"""The software rasteriser's threads: CPU and wall time per camera frame of the default episode with
Mesa's llvmpipe (behind PyBullet's EGL plugin) drawing in the calling thread, ``LP_NUM_THREADS=0``
(what ``dopeslam``'s render processes use where the variable is not set), and with threads of its
own, and whether the images come out as the same bytes.

Mesa reads the variable once, when the EGL display starts, so every measurement is a fresh process:
it renders the camera frames of the first ``--duration`` simulated seconds of the default scenario in
its own loop (no LiDAR, no render process; colour, depth and segmentation with their noise, as
``dopeslam run`` renders them) and reports, per frame, the process's CPU time over all its threads
(``time.process_time``) and the wall time, after ``--warmup`` frames. The settings alternate for
``--rounds`` rounds so that the machine's load falls on all of them alike. The table gives medians
over rounds and a SHA-256 of every frame's colour, depth and segmentation bytes.

    python benchmarks/bench_render_threads.py [--threads 0,2] [--rounds 3] [--duration 10] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MARK = "render-threads-result "


def child(duration: float, warmup: int) -> None:
    """Render the episode's frames here and print one result line (the parent parses it)."""
    import hashlib

    import numpy as np

    from sim.episode import Episode
    from stack.messages import CameraFrame

    h = hashlib.sha256()
    cpu = wall = 0.0
    n = 0
    with Episode(None, seed=0, duration=duration, lidar=False, render_worker=False) as ep:
        orig = ep._camera_frame

        def timed(t, T):
            nonlocal cpu, wall, n
            c0, w0 = time.process_time(), time.perf_counter()
            frame = orig(t, T)
            if n >= warmup:
                cpu += time.process_time() - c0
                wall += time.perf_counter() - w0
            n += 1
            return frame

        ep._camera_frame = timed
        for msg in ep.frames():
            if isinstance(msg, CameraFrame) and msg.rgb is not None:
                for a in (msg.rgb, msg.depth_m, msg.extra.get("segmentation")):
                    if a is not None:
                        h.update(np.ascontiguousarray(a).tobytes())
        renderer = ep.renderer
    timed_frames = max(n - warmup, 1)
    print(MARK + json.dumps({"frames": n, "cpu_ms": 1000 * cpu / timed_frames, "wall_ms": 1000 * wall / timed_frames,
                             "sha256": h.hexdigest(), "renderer": int(renderer)}), flush=True)


def measure(threads: str, duration: float, warmup: int) -> dict:
    env = dict(os.environ, LP_NUM_THREADS=threads, DOPESLAM_RENDER_WORKER="0")
    code = (f"import sys; sys.path.insert(0, {str(ROOT)!r}); sys.path.insert(0, {str(ROOT / 'benchmarks')!r}); "
            f"from bench_render_threads import child; child({duration!r}, {warmup!r})")
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True)
    lines = [line[len(MARK):] for line in out.stdout.splitlines() if line.startswith(MARK)]
    if out.returncode != 0 or not lines:
        raise SystemExit(f"bench_render_threads: the render process (LP_NUM_THREADS={threads}) failed with exit "
                         f"status {out.returncode}; its last output:\n{out.stderr[-2000:]}")
    return json.loads(lines[-1])


def table(rows: dict) -> str:
    first = next(iter(rows.values()))
    base = statistics.median(r["cpu_ms"] for r in first)
    lines = ["| LP_NUM_THREADS | frames | CPU ms per frame (median) | per round | wall ms per frame (median) | "
             "CPU vs the first | images |",
             "|---|---:|---:|---|---:|---:|---|"]
    ref = first[0]["sha256"]
    for threads, rs in rows.items():
        cpu = statistics.median(r["cpu_ms"] for r in rs)
        wall = statistics.median(r["wall_ms"] for r in rs)
        same = all(r["sha256"] == ref for r in rs)
        per_round = ", ".join(f"{r['cpu_ms']:.1f}" for r in rs)
        lines.append(f"| {threads} | {rs[0]['frames']} | {cpu:.1f} | {per_round} | "
                     f"{wall:.1f} | {100 * (cpu / base - 1):+.0f} % | {'same bytes' if same else 'DIFFERENT'} "
                     f"({rs[0]['sha256'][:12]}) |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", default="0,2", help="LP_NUM_THREADS values, comma-separated (the first is the "
                                                     "reference for the CPU ratio and the image bytes)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds per process")
    ap.add_argument("--warmup", type=int, default=5, help="frames not timed at the start of each process")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    values = [v.strip() for v in args.threads.split(",") if v.strip()]
    if not values or any(not v.isdigit() for v in values):
        ap.error(f"--threads: expected comma-separated integers >= 0, got {args.threads!r}")
    if args.rounds < 1 or args.duration <= 0 or args.warmup < 0:
        ap.error("--rounds >= 1, --duration > 0 and --warmup >= 0 expected")
    rows: dict[str, list[dict]] = {v: [] for v in values}
    t0 = time.perf_counter()
    total = args.rounds * len(values)
    for i in range(args.rounds):
        for v in values:
            rows[v].append(measure(v, args.duration, args.warmup))
            done = sum(len(r) for r in rows.values())
            eta = (time.perf_counter() - t0) / done * (total - done)
            print(f"  round {i + 1}/{args.rounds}, LP_NUM_THREADS={v}: {rows[v][-1]['cpu_ms']:.1f} CPU ms per frame "
                  f"(ETA {eta:.0f} s)", file=sys.stderr, flush=True)
    import pybullet as p

    if next(iter(rows.values()))[0]["renderer"] != p.ER_BULLET_HARDWARE_OPENGL:
        print("note: the EGL renderer did not load here; TinyRenderer has no rasteriser threads")
    print(f"default scenario, seed 0, {args.duration:g} simulated s per process, {args.rounds} rounds alternating; "
          f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print(table(rows))
    if args.json:
        from stack.io import write_json

        write_json(args.json, {"args": vars(args), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
