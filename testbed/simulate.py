"""``dopeslam simulate``: run an episode with every sensor and write what it produced."""
from __future__ import annotations

import logging
import time
from pathlib import Path

import cv2
import numpy as np

from sim.episode import Episode
from stack.messages import CameraFrame, LidarScan
from stack.metrics import write_tum
from testbed.io import write_json
from testbed.plots import save, scene_figure

log = logging.getLogger(__name__)




def run_simulation(scenario=None, out_dir="out/simulate", seed=None, duration=None, samples: int = 3,
                   render_worker: bool | int | None = 2) -> dict:
    """Every sensor of an episode, no stack. Nothing here reads a segmentation image, so none is
    rendered; the camera renders in two more processes, frames alternating (``render_worker``; the
    same frames), so the physics, the LiDAR and the renderer keep both cores busy."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wall0 = time.perf_counter()
    with Episode(scenario, seed=seed, duration=duration, segmentation=False, render_worker=render_worker) as ep:
        cams = lids = 0
        points = []
        sample_at = set(np.linspace(0, max(1, int(ep.duration * ep.sc.sensors.camera_rate)) - 1, samples).astype(int))
        last_report = time.perf_counter()
        for msg in ep.frames():
            if isinstance(msg, CameraFrame):
                if cams in sample_at:
                    if msg.rgb is not None:
                        cv2.imwrite(str(out / f"rgb_{cams:05d}.png"), msg.rgb[..., ::-1])
                    if msg.depth_m is not None:
                        cv2.imwrite(str(out / f"depth_{cams:05d}.png"), np.clip(msg.depth_m * 1000, 0, 65535).astype(np.uint16))
                cams += 1
            elif isinstance(msg, LidarScan):
                points.append(len(msg.points))
                if lids == 0:
                    np.savez_compressed(out / "lidar_scan.npz", points=msg.points, times_s=msg.times_s,
                                        ring=msg.ring, intensity=msg.intensity, stamp=msg.stamp)
                lids += 1
            if time.perf_counter() - last_report > 10:
                last_report = time.perf_counter()
                log.info("sim t = %.1f / %.1f s", getattr(msg, "stamp", 0.0), ep.duration)
        wall = time.perf_counter() - wall0
        gt = ep.groundtruth
        stride = max(1, int(round(ep.sc.physics_hz / 30)))  # ground truth at 30 Hz
        write_tum(out / "groundtruth_tum.txt", gt.stamps[::stride], gt.T_world_base[::stride])
        fig, ax = scene_figure(ep.world, ep.sc.route, gt.T_world_base[:, :2, 3], f"{ep.sc.name} (seed {ep.seed})")
        save(fig, out / "scene_topdown.png")
        summary = {
            "scenario": ep.sc.name, "seed": ep.seed, "sim_seconds": ep.sim_seconds, "wall_seconds": wall,
            "real_time_factor": ep.sim_seconds / wall, "camera_frames": cams, "lidar_scans": lids,
            "lidar_points_per_scan": float(np.mean(points)) if points else 0.0,
            "waypoint_closest_m": [float(x) for x in ep.follower.closest], "route_completed": ep.follower.done,
        }
    write_json(out / "summary.json", summary)
    return summary
