"""``dopeslam odometry``: one episode's LiDAR odometry (KISS-ICP) and wheel odometry scored against
the simulator's ground truth.

Outputs in ``out_dir``:

* ``odometry.json``: ``ate_rmse_m`` (estimate placed in ``world`` by the known start pose),
  ``ate_rmse_umeyama_m`` (SE(3)-aligned, as ``evo_ape -a``), ``rpe_trans_pct``,
  ``rpe_rot_deg_per_m`` (over 1 m of travel, see ``stack.metrics``), ``scans``, ``odometry_hz``,
  and the same figures for wheel odometry under ``wheel_odometry``;
* ``estimate_tum.txt`` and ``groundtruth_tum.txt``: the same timestamps, both in ``world``, so that
  ``evo_ape tum groundtruth_tum.txt estimate_tum.txt`` prints our ``ate_rmse_m`` (and with ``-a``
  our ``ate_rmse_umeyama_m``); ``wheel_odometry_tum.txt`` likewise for the wheels;
* ``odometry_topdown.png``: both trajectories over the accumulated LiDAR map.

The known start pose: ``map`` is ``base_link`` at the first registered scan, so the estimate goes to
``world`` through the true ``T_world_base`` at that scan's pose stamp.
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np

from sim.episode import Episode
from stack import metrics
from stack.errors import InputDataError
from stack.interfaces import check_trajectory
from stack.lidar_slam import LidarOdometryConfig
from stack.messages import CameraFrame, LidarScan, WheelOdometry
from stack.transforms import transform_points, voxel_thin
from testbed.io import write_json
from testbed.plots import save

log = logging.getLogger(__name__)

RPE_DELTA_M = 1.0
MAP_VOXEL_M = 0.05  # resolution of the accumulated map drawn under the trajectories


def score(stamps: np.ndarray, T_map_base: np.ndarray, T_world_base_gt: np.ndarray) -> dict:
    """ATE / RPE of a trajectory already matched in time to its ground truth (map placed by gt[0])."""
    est = T_world_base_gt[0] @ T_map_base
    r = metrics.rpe(est, T_world_base_gt, RPE_DELTA_M)
    length = float(metrics.path_length(T_world_base_gt)[-1])
    return {
        "ate_rmse_m": metrics.ate_rmse(est, T_world_base_gt),
        "ate_rmse_umeyama_m": metrics.ate_rmse_umeyama(est, T_world_base_gt) if len(est) >= 3 else float("nan"),
        "rpe_trans_pct": r.trans_pct,
        "rpe_rot_deg_per_m": r.rot_deg_per_m,
        "rpe_delta_m": r.delta_m,
        "rpe_pairs": r.pairs,
        "path_length_m": length,
        "final_error_m": float(np.linalg.norm(est[-1, :3, 3] - T_world_base_gt[-1, :3, 3])),
    }


class _MapAccumulator:
    """Registered scans in ``map``, thinned to one point per voxel."""

    def __init__(self, voxel: float = MAP_VOXEL_M, compact_every: int = 500_000):
        self.voxel = voxel
        self.compact_every = compact_every
        self.chunks: list[np.ndarray] = []
        self.count = 0

    def add(self, points_map: np.ndarray) -> None:
        self.chunks.append(points_map)
        self.count += len(points_map)
        if self.count > self.compact_every:
            self._compact()

    def _compact(self) -> None:
        if not self.chunks:
            return
        self.chunks = [voxel_thin(np.concatenate(self.chunks), self.voxel)]
        self.count = len(self.chunks[0])

    def points(self) -> np.ndarray:
        self._compact()
        return self.chunks[0] if self.chunks else np.empty((0, 3))


def _topdown_png(path: Path, map_world: np.ndarray, gt: np.ndarray, est: np.ndarray,
                 wheel: np.ndarray | None, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 7))
    if len(map_world):
        keep = (map_world[:, 2] > 0.05) & (map_world[:, 2] < 2.0)  # walls and furniture, not floor/ceiling
        ax.scatter(map_world[keep, 0], map_world[keep, 1], s=0.2, c="0.55", lw=0)
        ax.plot([], [], ".", color="0.55", label="LiDAR map (placed by the estimate)")
    ax.plot(gt[:, 0, 3], gt[:, 1, 3], "k-", lw=2.0, label="ground truth")
    ax.plot(est[:, 0, 3], est[:, 1, 3], "-", color="tab:red", lw=1.2, label="KISS-ICP odometry")
    if wheel is not None and len(wheel):
        ax.plot(wheel[:, 0, 3], wheel[:, 1, 3], "--", color="tab:blue", lw=1.0, label="wheel odometry")
    ax.plot(gt[0, 0, 3], gt[0, 1, 3], "go", ms=6, label="start")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="lower left", fontsize=7, framealpha=0.8)
    save(fig, path)


def run_odometry(scenario=None, seed: int | None = None, out_dir: str | os.PathLike = "out/odometry",
                 duration: float | None = None, wheel: bool = True, config: LidarOdometryConfig | None = None,
                 T_base_velodyne: np.ndarray | None = None, plot: bool = True, loop_closure: bool = False,
                 odometry=None, loop_closure_config=None) -> dict:
    """Run an episode with the LiDAR (no camera), odometry on every scan, score, write the outputs.

    The episode's messages go through the stack's pipeline (:class:`stack.pipeline.DopeSlam`) with no
    detector, as ``dopeslam run`` sends them. ``odometry``: None (KISS-ICP with ``config``), a name
    for :func:`stack.interfaces.load_odometry` (``wheel``, ``MODULE:CLASS``, an entry point's name) or
    a callable ``T_base_lidar -> Odometry``. ``T_base_velodyne`` overrides the extrinsic the odometry
    is given (the episode's otherwise), to show what a miscalibrated robot does. Returns the
    ``odometry.json`` contents.

    ``loop_closure``: the camera runs too (key frames only) and a loop closer (``testbed/loop_closing.py``,
    settings ``loop_closure_config``, a ``stack.config.LoopClosureSection``) corrects the trajectory;
    ``ate_rmse_m`` is then the closed-loop figure, and ``odometry.json`` adds ``loop_closures``,
    ``loop_candidates_rejected``, ``false_loop_closures``, ``ate_rmse_odometry_only_m``.
    """
    from stack.pipeline import DopeSlam
    from testbed.run import detector_name, make_odometry

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wall0 = time.perf_counter()
    lc = None
    if loop_closure:
        from testbed.loop_closing import LoopClosingRun, key_frame_scenario

        section = loop_closure_config
        scenario, lc_config = key_frame_scenario(scenario, None if section is None else section.closure_config())
        lc = LoopClosingRun(None if section is None else section.vocabulary, config=lc_config)
    with Episode(scenario, seed=seed, duration=duration, camera=loop_closure, lidar=True) as ep:
        E = ep.T_base_velodyne if T_base_velodyne is None else np.asarray(T_base_velodyne, dtype=float)
        odo = make_odometry(odometry, E, config)
        pipe = DopeSlam(odo, None, ep.T_base_camera, {}, loop_closer=lc, map_objects=False)
        accumulated = _MapAccumulator()
        scans = 0
        last_report = time.perf_counter()
        for msg in ep.frames():
            if isinstance(msg, LidarScan):
                scans += 1
                T_map_base = pipe.on_scan(msg)
                points = getattr(odo, "last_points_base", None)
                if T_map_base is not None and points is not None:
                    accumulated.add(transform_points(T_map_base, points))
            elif isinstance(msg, CameraFrame):
                if lc is not None:
                    pipe.on_image(msg)
            elif isinstance(msg, WheelOdometry):
                pipe.on_wheel_odometry(msg)
            if time.perf_counter() - last_report > 10.0:
                last_report = time.perf_counter()
                log.info("odometry: sim t = %.1f / %.1f s, %d scans, %d registered", msg.stamp, ep.duration,
                         scans, pipe.registered)
        registered = len(check_trajectory(odo, odo.trajectory())[0])
        if registered < 2:
            raise InputDataError(f"{ep.sc.name}: {registered} scan(s) registered in {ep.duration:g} s; nothing to "
                                 "score (a longer --duration, or an odometry that registers the scans)")
        result = pipe.finish()
        stamps, T_odom, T_map_base = result.stamps, result.T_map_base_odometry, result.T_map_base
        gt = ep.T_world_base_at(stamps)
        T_world_map = gt[0]
        if lc is not None:  # the closed-loop trajectory is the estimate; its map is placed with it
            accumulated = _MapAccumulator()
            for pts in result.map_points:
                accumulated.add(pts)
        est = T_world_map @ T_map_base
        report = {"scenario": ep.sc.name, "seed": ep.seed, "sim_seconds": float(ep.duration)}
        report.update(score(stamps, T_map_base, gt))
        stats = getattr(odo, "stats", None)
        seconds = pipe.timing["odometry"]
        report.update({
            "scans": stats.scans_in if stats is not None else scans,
            "scans_registered": stats.scans_used if stats is not None else pipe.registered,
            "odometry_hz": stats.hz if stats is not None else (scans / seconds if seconds > 0 else None),
            "odometry_seconds": stats.seconds if stats is not None else seconds,
            "episode_wall_seconds": time.perf_counter() - wall0,
            "T_base_velodyne": E.tolist(),
            "map_origin_offset_m": float(np.linalg.norm(T_world_map[:3, 3] - ep.T_world_map[:3, 3])),
        })
        if stats is not None:
            report["warnings"] = {k: v for k, v in vars(stats).items() if k not in ("scans_in", "scans_used", "seconds")}
        if getattr(odo, "config", None) is not None:
            report["config"] = odo.config.model_dump()
        report["odometry_component"] = detector_name(odo)
        if lc is not None:
            report.update(lc.summary(stamps, T_odom, T_map_base, T_world_map, ep.T_world_base_at))
        metrics.write_tum(out / "estimate_tum.txt", stamps, est)
        metrics.write_tum(out / "groundtruth_tum.txt", stamps, gt)

        wheel_world = None
        if wheel and len(result.wheel_stamps) >= 2:
            w_stamps, w_poses = result.wheel_stamps, result.T_odom_base
            w_gt = ep.T_world_base_at(w_stamps)
            report["wheel_odometry"] = {"messages": len(pipe.wheel), **score(w_stamps, w_poses, w_gt)}
            wheel_world = w_gt[0] @ w_poses
            metrics.write_tum(out / "wheel_odometry_tum.txt", w_stamps, wheel_world)
            metrics.write_tum(out / "wheel_groundtruth_tum.txt", w_stamps, w_gt)

        if plot:
            title = (f"{ep.sc.name} seed {ep.seed}: odometry ATE {100 * report['ate_rmse_m']:.1f} cm, "
                     f"RPE {report['rpe_trans_pct']:.2f} %")
            if "wheel_odometry" in report:
                title += f"; wheels ATE {100 * report['wheel_odometry']['ate_rmse_m']:.1f} cm"
            _topdown_png(out / "odometry_topdown.png", transform_points(T_world_map, accumulated.points()),
                         gt, est, wheel_world, title)
    write_json(out / "odometry.json", report)
    return report
