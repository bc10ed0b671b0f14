"""DOPE speed per 640x480 camera frame for 1..6 stages (all six classes in one pass), RGB and depth input.

A frame is rendered with the simulator (several objects in view at 0.5-1.5 m) and passed to
``DopeDetector.detect`` (resize to the network's 320x240, network, peaks, association, PnP, FPR)
``--repeats`` times per stage count. Reported: median wall ms per frame, frames per second, CPU ms per
frame (process CPU time: what it costs on an otherwise idle machine), the 1-vs-6-stage speed-up, and
the load average (wall time depends on what else runs on the machine).

    python benchmarks/bench_dope.py [--repeats 15] [--threads 2] [--weights W] [--depth] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch


def build_scene(client: int) -> dict:
    """A floor and three objects 0.8-1.4 m ahead of the origin in ``client``; the class catalogue."""
    import pybullet as p

    from sim.objects import load_catalog, spawn_object

    cat = load_catalog()
    floor = p.createVisualShape(p.GEOM_BOX, halfExtents=[5, 5, 0.05], rgbaColor=[0.6, 0.6, 0.55, 1], physicsClientId=client)
    p.createMultiBody(0, -1, floor, [0, 0, -0.05], physicsClientId=client)
    for i, (cls, x, y) in enumerate((("E", 0.8, 0.0), ("Mustard", 1.1, 0.3), ("Cookies", 1.4, -0.35))):
        spawn_object(client, cat[cls], cat[cls].standing_pose([x, y, 0.0], np.pi + 0.3 * i))
    return cat


def render_frame():
    import pybullet as p

    from sim.camera import default_camera_info, new_client, render_rgbd

    client, renderer = new_client("tiny")
    cat = build_scene(client)
    info = default_camera_info()
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    T[:3, 3] = [0, 0, 0.3]
    rgb, depth, _ = render_rgbd(client, T, info, rng=np.random.default_rng(0))
    p.disconnect(client)
    dims = {c: s.dims for c, s in cat.items()}
    return info, rgb, depth, dims


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--depth", action="store_true", help="also time the depth input (sliding windows and one window)")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from stack.dope_fpr import DopeDetector
    from stack.messages import CameraFrame

    info, rgb, depth, dims = render_frame()
    frame = CameraFrame(0.0, info, rgb=rgb, depth_m=depth)
    configs = [("rgb", None)]
    if args.depth:
        configs += [("depth", [(0.65, 0.95)]), ("depth", None)]
    rows = []
    for mode, windows in configs:
        for stages in range(1, 7):
            det = DopeDetector(weights=args.weights if mode == "rgb" else None, input=mode, stages=stages, dims=dims,
                               depth_windows=windows)
            det.detect(frame)  # warm-up
            walls, cpus = [], []
            for _ in range(args.repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                dets = det.detect(frame)
                walls.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            wall = float(np.median(walls))
            label = mode if mode == "rgb" else ("depth 1 window" if windows else f"depth {len(det.depth_windows)} windows")
            rows.append({"input": label, "stages": stages, "layers": det.model.layer_count(stages),
                         "wall_ms": 1000 * wall, "fps": 1.0 / wall, "cpu_ms": 1000 * float(np.median(cpus)),
                         "detections": len(dets)})
    print(f"load average {os.getloadavg()[0]:.2f}, torch threads {torch.get_num_threads()}, frame 640x480 -> 320x240")
    print(f"{'input':<18} {'stages':>6} {'layers':>6} {'wall ms':>8} {'fps':>6} {'cpu ms':>7} {'dets':>5}")
    for r in rows:
        print(f"{r['input']:<18} {r['stages']:>6} {r['layers']:>6} {r['wall_ms']:8.1f} {r['fps']:6.2f} {r['cpu_ms']:7.1f} {r['detections']:>5}")
    for label in dict.fromkeys(r["input"] for r in rows):
        one = next(r for r in rows if r["input"] == label and r["stages"] == 1)
        six = next(r for r in rows if r["input"] == label and r["stages"] == 6)
        print(f"{label}: 1-vs-6-stage speed-up {six['wall_ms'] / one['wall_ms']:.2f}x (paper 2.6x)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"load_average": os.getloadavg()[0], "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
