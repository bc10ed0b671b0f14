"""``--loop-closure`` for the harness (``dopeslam run``, ``dopeslam odometry``): one object that rides
along the odometry loop, then corrects the trajectory, re-places the labels and scores the closures.

The pieces it wires are the stack's (:mod:`stack.loops.closure`, :mod:`stack.loops.place_recognition`); the
scoring of closures against ground truth is the testbed's: a closure is *false* when its registered
relative pose is further than ``FALSE_CLOSURE_M`` / ``FALSE_CLOSURE_DEG`` from the true one (for two
different places that is metres).

Labels move with closures: every detection that was fused with the odometry is kept and fused again at
the end with the corrected trajectory (``C(t) @ T_map_base_odometry(t)``), into a fresh object store.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from stack.fusion import fuse
from stack.loops.closure import LoopCloser, LoopClosureConfig
from stack.messages import CameraFrame, Detection
from stack.metrics import ate_rmse
from stack.loops.place_recognition import VocabularyTree
from stack.transforms import inv, transform_points

log = logging.getLogger(__name__)

FALSE_CLOSURE_M = 0.3
FALSE_CLOSURE_DEG = 5.0


class LoopClosingRun:
    def __init__(self, vocabulary: str | Path | VocabularyTree | None = None, config: LoopClosureConfig | None = None,
                 map_every: int = 5):
        if isinstance(vocabulary, VocabularyTree):
            tree = vocabulary
        elif vocabulary is not None:
            tree = VocabularyTree.load(vocabulary)
        else:
            from testbed.vocabulary import default_vocabulary

            tree = default_vocabulary()
        self.closer = LoopCloser(tree, config)
        self.detections: list[Detection] = []
        self.seconds = 0.0
        self._map_every = map_every
        self._map: list[tuple[float, np.ndarray, np.ndarray]] = []  # (stamp, odometry pose, points in base_link)
        self._scans = 0

    # ------------------------------------------------------------------ during the run

    def on_scan(self, odom, T_map_base: np.ndarray | None) -> None:
        """After ``odom.process(scan)``: its pose (None when the scan was skipped)."""
        points = getattr(odom, "last_points_base", None)  # an odometry without points: no LiDAR key frames
        if T_map_base is None or points is None:
            return
        t0 = time.perf_counter()
        last = getattr(odom, "last_stamp", None)
        stamp = float(last() if callable(last) else odom.trajectory()[0][-1])
        self.closer.add_scan(stamp, T_map_base, points)
        if self._scans % self._map_every == 0:
            pts = points[::4].astype(np.float32)
            self._map.append((stamp, np.asarray(T_map_base, dtype=float), pts))
        self._scans += 1
        self.seconds += time.perf_counter() - t0

    def on_image(self, frame: CameraFrame) -> None:
        t0 = time.perf_counter()
        self.closer.add_image(frame.stamp, frame.rgb)
        self.seconds += time.perf_counter() - t0

    def on_fused(self, detection: Detection) -> None:
        """A detection that was fused into the map with the odometry (kept to be fused again)."""
        self.detections.append(detection)

    # ------------------------------------------------------------------ after the run

    def finish(self, stamps: np.ndarray, T_map_base_odom: np.ndarray) -> np.ndarray:
        """Final optimisation; the corrected ``T_map_base`` at the odometry's stamps."""
        t0 = time.perf_counter()
        self.closer.finalise()
        out = self.closer.correct(stamps, T_map_base_odom)
        self.seconds += time.perf_counter() - t0
        return out

    def pose_lookup(self, odom_pose_at):
        """t -> corrected ``T_map_base`` (None where the odometry has none)."""
        def lookup(t: float):
            T = odom_pose_at(t)
            return None if T is None else self.closer.correct(t, T)
        return lookup

    def refuse(self, store, odom_pose_at, T_base_cam: np.ndarray):
        """Fuse every kept detection again, with the corrected trajectory, into ``store`` (a fresh one)."""
        lookup = self.pose_lookup(odom_pose_at)
        for det in self.detections:
            if lookup(det.stamp) is not None:
                store.add(fuse(det, lookup, T_base_cam))
        return store

    def map_points(self) -> list[np.ndarray]:
        """The LiDAR map (every ``map_every``-th scan, a quarter of its points) placed with the corrected
        trajectory, in ``map``."""
        if not self._map:
            return []
        stamps = np.array([m[0] for m in self._map])
        T = self.closer.correct(stamps, np.array([m[1] for m in self._map]))
        return [transform_points(Ti, m[2]) for Ti, m in zip(T, self._map)]

    def summary(self, stamps: np.ndarray, T_odom: np.ndarray, T_corrected: np.ndarray, T_world_map: np.ndarray,
                T_world_base_at) -> dict:
        """The odometry.json / report keys: closures accepted, candidates rejected, false closures (against
        ground truth), ATE with and without the closures."""
        gt = T_world_base_at(stamps)
        false = []
        for c in self.closer.closures:
            truth = inv(T_world_base_at(c.candidate_stamp)) @ T_world_base_at(c.query_stamp)
            err = inv(truth) @ c.T_cand_query
            e_m = float(np.linalg.norm(err[:3, 3]))
            e_deg = float(np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))))
            if e_m > FALSE_CLOSURE_M or e_deg > FALSE_CLOSURE_DEG:
                false.append({**c.as_dict(), "error_m": e_m, "error_deg": e_deg})
        s = self.closer.summary()
        return {
            "loop_closures": s["loop_closures"], "loop_candidates_rejected": s["loop_candidates_rejected"],
            "false_loop_closures": len(false), "ate_rmse_odometry_only_m": ate_rmse(T_world_map @ T_odom, gt),
            "loop_closure": {**s, "false_closures": false,
                             "false_closure_threshold": [FALSE_CLOSURE_M, FALSE_CLOSURE_DEG],
                             "seconds_total": self.seconds,
                             "closures": [c.as_dict() for c in self.closer.closures]},
        }


# ---------------------------------------------------------------------------------------------
# LiDAR odometry + loop closure on a scenario, without DOPE: the trajectory figures


def key_frame_scenario(scenario, config: LoopClosureConfig | None = None):
    """(scenario, config) for a run that needs the camera only for key frames: the camera runs at its
    rate / ``keyframe_every`` and every image it gives is a key frame (the same images as one in ten
    at the full rate, a tenth of the rendering)."""
    from sim.scenario import load_scenario

    cfg = (config or LoopClosureConfig()).model_copy()
    sc = scenario.model_copy(deep=True) if hasattr(scenario, "sensors") else load_scenario(scenario)
    sc.sensors.camera_rate = sc.sensors.camera_rate / cfg.keyframe_every
    cfg.keyframe_every = 1
    return sc, cfg


def run_loop_closure(scenario: str = "office_loop", out_dir: str = "out/loop_closure", seed: int | None = None,
                     duration: float | None = None, vocabulary: str | None = None,
                     config: LoopClosureConfig | None = None, odometry=None) -> dict:
    """The odometry (KISS-ICP, or ``odometry``: see ``testbed.run.make_odometry``) and the loop closer
    over an episode, driven by the stack's pipeline (:class:`stack.pipeline.DopeSlam`) without a
    detector; ``loop_closure.json`` and ``loop_closure.png`` (ground truth, odometry, closed-loop
    trajectory, accepted closures).

    Only the key frames are rendered: the camera runs at its rate / ``keyframe_every`` and every
    image it gives is a key frame (the same images as one in ten at the full rate)."""
    from sim.episode import Episode
    from stack.metrics import ate_rmse_umeyama, rpe
    from stack.pipeline import DopeSlam
    from testbed.run import make_odometry
    from testbed.io import write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc, cfg = key_frame_scenario(scenario, config)
    lc = LoopClosingRun(vocabulary, cfg)
    wall0 = last = time.perf_counter()
    with Episode(sc, seed=seed, duration=duration) as ep:
        pipe = DopeSlam(make_odometry(odometry, ep.T_base_velodyne), None, ep.T_base_camera, {}, loop_closer=lc)
        for msg in ep.frames():
            pipe.on_message(msg)
            if time.perf_counter() - last > 30:
                last = time.perf_counter()
                log.info("t = %.0f of %.0f s: %d key frames, %d closures, %d rejected", msg.stamp, ep.duration,
                         lc.closer.stats.key_frames, lc.closer.stats.accepted, lc.closer.stats.rejected)
        result = pipe.finish()
        stamps, T_odom, T_lc = result.stamps, result.T_map_base_odometry, result.T_map_base
        t_odom = pipe.timing["odometry"]
        T_world_map = ep.T_world_base_at(stamps[0])
        gt = ep.T_world_base_at(stamps)
        report = {"scenario": ep.sc.name, "seed": ep.seed, "sim_seconds": ep.sim_seconds,
                  "wall_seconds": time.perf_counter() - wall0, "odometry_seconds": t_odom,
                  "ate_rmse_m": ate_rmse(T_world_map @ T_lc, gt),
                  "ate_rmse_umeyama_m": ate_rmse_umeyama(T_world_map @ T_lc, gt),
                  "ate_rmse_odometry_only_umeyama_m": ate_rmse_umeyama(T_world_map @ T_odom, gt),
                  "rpe_trans_pct": rpe(T_world_map @ T_lc, gt).trans_pct,
                  "rpe_trans_pct_odometry_only": rpe(T_world_map @ T_odom, gt).trans_pct,
                  **lc.summary(stamps, T_odom, T_lc, T_world_map, ep.T_world_base_at)}
        report["ate_ratio"] = report["ate_rmse_m"] / report["ate_rmse_odometry_only_m"]
        write_json(out / "loop_closure.json", report)
        _trajectory_png(out / "loop_closure.png", ep, T_world_map, stamps, T_odom, T_lc, lc, report)
    return report


def _trajectory_png(path, ep, T_world_map, stamps, T_odom, T_lc, lc: LoopClosingRun, report) -> None:
    from testbed.plots import plt, save

    fig, ax = plt.subplots(figsize=(12, 4.5))
    for b in ep.world.boxes:
        if b.half[2] > 0.2 and max(b.half[:2]) < 30:  # furniture, walls (not floor, ceiling)
            c = transform_points(b.T_world_box, np.array([[sx * b.half[0], sy * b.half[1], 0] for sx, sy in
                                                          ((-1, -1), (1, -1), (1, 1), (-1, 1), (-1, -1))]))
            ax.fill(c[:, 0], c[:, 1], color="0.85", lw=0)
    gt = ep.T_world_base_at(stamps)[:, :2, 3]
    odo = (T_world_map @ T_odom)[:, :2, 3]
    cor = (T_world_map @ T_lc)[:, :2, 3]
    ax.plot(gt[:, 0], gt[:, 1], "g-", lw=1.2, label="ground truth")
    ax.plot(odo[:, 0], odo[:, 1], "b--", lw=0.8,
            label=f"LiDAR odometry (ATE {100 * report['ate_rmse_odometry_only_m']:.1f} cm)")
    ax.plot(cor[:, 0], cor[:, 1], "r-", lw=0.8, label=f"with loop closure (ATE {100 * report['ate_rmse_m']:.1f} cm)")
    kst = np.array([k.stamp for k in lc.closer.key_frames])
    kpos = (T_world_map @ np.array(lc.closer.T_opt))[:, :2, 3] if len(kst) else np.zeros((0, 2))
    for c in lc.closer.closures:
        a, b = kpos[c.candidate], kpos[c.query]
        ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="orange" if c.source == "appearance" else "purple", lw=1.5)
    ax.plot([], [], "-", color="orange", label="closure (retrieval)")
    ax.plot([], [], "-", color="purple", label="closure (LiDAR proximity)")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.legend(fontsize=7, loc="upper right", ncol=2)
    ax.set_title(f"{report['scenario']}: {report['loop_closures']} loop closures "
                 f"({report['false_loop_closures']} false), {report['loop_candidates_rejected']} candidates rejected",
                 fontsize=9)
    save(fig, path)


def add_arguments(p) -> None:
    """The options of ``dopeslam loop-closure``."""
    p.add_argument("scenario", nargs="?", default="office_loop")
    p.add_argument("--out", default="out/loop_closure")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--vocabulary", default=None, help="vocabulary .npz (default: built from the training scenarios)")
    p.add_argument("--proximity", choices=["fallback", "always", "never"], default=None,
                   help="LiDAR-proximity candidates (default: fallback, when retrieval has none)")
    from testbed.commands.run import add_odometry_option

    add_odometry_option(p)


def run_args(a) -> int:
    import sys

    from stack.interfaces import ImportPathError, odometry_factory

    cfg = LoopClosureConfig(**({"proximity": a.proximity} if a.proximity else {}))
    try:
        odometry_factory(a.odometry)
        r = run_loop_closure(a.scenario, a.out, a.seed, a.duration, a.vocabulary, cfg, odometry=a.odometry)
    except ImportPathError as e:
        print(f"dopeslam loop-closure: --{e}", file=sys.stderr)
        return 2
    print(f"{r['scenario']}: {r['sim_seconds']:.0f} s simulated in {r['wall_seconds']:.0f} s; "
          f"{r['loop_closures']} loop closures ({r['false_loop_closures']} false), "
          f"{r['loop_candidates_rejected']} candidates rejected")
    print(f"ATE {100 * r['ate_rmse_m']:.1f} cm with loop closure, {100 * r['ate_rmse_odometry_only_m']:.1f} cm "
          f"odometry only (ratio {r['ate_ratio']:.2f}); Umeyama-aligned {100 * r['ate_rmse_umeyama_m']:.1f} / "
          f"{100 * r['ate_rmse_odometry_only_umeyama_m']:.1f} cm")
    print(f"wrote {a.out}/loop_closure.json, loop_closure.png")
    return 0
