"""``--loop-closure`` for the harness (``dopeslam run``, ``dopeslam odometry``): one object that rides
along the odometry loop, then corrects the trajectory, re-places the labels and scores the closures.

The pieces it wires are the stack's (:mod:`stack.loop_closure`, :mod:`stack.place_recognition`); the
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
from stack.loop_closure import LoopCloser, LoopClosureConfig
from stack.messages import CameraFrame, Detection
from stack.metrics import ate_rmse
from stack.place_recognition import VocabularyTree
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
        if T_map_base is None or odom.last_points_base is None:
            return
        t0 = time.perf_counter()
        stamp = float(odom.trajectory()[0][-1])
        self.closer.add_scan(stamp, T_map_base, odom.last_points_base)
        if self._scans % self._map_every == 0:
            self._map.append((stamp, np.asarray(T_map_base, dtype=float), odom.last_points_base[::4].astype(np.float32)))
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
            "loop_closure": {**s, "false_closures": false, "false_closure_threshold": [FALSE_CLOSURE_M, FALSE_CLOSURE_DEG],
                             "seconds_total": self.seconds,
                             "closures": [c.as_dict() for c in self.closer.closures]},
        }
