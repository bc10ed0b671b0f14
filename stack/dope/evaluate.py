"""DOPE accuracy on held-out rendered shards, and FPR calibration from them.

For every image of the chosen shards the detector runs once (all stage counts from one pass); each
detection is matched to the nearest ground-truth object of its class. A detection is correct when it
is within 5 cm of the truth along every camera axis (the paper's false-positive rule). From the same
pass: detection rate of objects 0.5-1.5 m away and at least half visible, position error, ADD pass
rate (mean key-point distance below 10 % of the cuboid diagonal), and the (class, stages, belief_sum,
correct) records that :meth:`stack.dope_fpr.FprThresholds.calibrate` turns into thresholds.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from stack.dope_fpr import DopeDetector, cuboid_points
from stack.errors import InputDataError
from stack.messages import CameraFrame, CameraInfo

log = logging.getLogger(__name__)
FALSE_POSITIVE_M = 0.05


def load_shard_frames(data_dir, shard_ids, classes):
    """Yield (CameraFrame, [truth dicts]) for every image of the given shards."""
    data_dir = Path(data_dir)
    for sid in shard_ids:
        npz = data_dir / f"shard_{sid:05d}.npz"
        try:
            meta = json.loads(npz.with_suffix(".json").read_text())
            arr = np.load(npz)
        except (OSError, ValueError) as exc:
            raise InputDataError(f"{npz}: unreadable DOPE data shard ({exc})") from exc
        info = CameraInfo(int(meta["width"]), int(meta["height"]), np.array(meta["K"], dtype=float))
        for i, image in enumerate(meta["images"]):
            truths = []
            for o in image["objects"]:
                if o["class"] not in classes:
                    continue
                T = np.eye(4)
                T[:3, :3] = Rotation.from_quat(o["quaternion_xyzw"]).as_matrix()
                T[:3, 3] = o["location"]
                truths.append({"cls": o["class"], "T_cam_obj": T, "visible": o["pixels_visible"] / max(o["hull_area_px"], 1.0),
                               "pixels": o["pixels_visible"], "keypoints_px": np.array(o["keypoints_px"])})
            frame = CameraFrame(stamp=float(sid * 1000 + i), info=info, rgb=arr["rgb"][i],
                                depth_m=arr["depth_mm"][i].astype(np.float32) / 1000.0)
            yield frame, truths


def add_error(T_est, T_true, dims, half_turn: bool = True) -> float:
    """ADD: mean distance of the cuboid's key points under the two poses. With ``half_turn`` the truth may
    also be turned half about its vertical axis (the symmetry the training labels resolve by view, see
    :func:`stack.dope.train.canonical_order`); the smaller error counts."""
    pts = cuboid_points(dims)
    a = pts @ T_est[:3, :3].T + T_est[:3, 3]
    cands = [T_true[:3, :3]]
    if half_turn:
        up = int(np.argmax(np.abs(T_true[1, :3])))
        g = -np.ones(3)
        g[up] = 1
        cands.append(T_true[:3, :3] @ np.diag(g))
    return float(min(np.mean(np.linalg.norm(a - (pts @ R.T + T_true[:3, 3]), axis=1)) for R in cands))


def evaluate(detector: DopeDetector, data_dir, shard_ids, near_far=(0.5, 1.5), min_visible=0.5,
             stage_counts=(1, 2, 3, 4, 5, 6), progress: bool = True) -> dict:
    """Per stage count: detection rate, precision (FPR off / on), median position error, ADD pass rate;
    and ``records`` for FPR calibration."""
    from tqdm import tqdm

    stats = {s: {"instances": 0, "found": 0, "pos_err": [], "add_pass": 0, "dets": 0, "correct": 0,
                 "dets_fpr": 0, "correct_fpr": 0, "found_fpr": 0} for s in stage_counts}
    records = []
    frames = list(load_shard_frames(data_dir, shard_ids, detector.classes))
    for frame, truths in tqdm(frames, desc="dope eval", unit="img", disable=not progress):
        by_stage = detector.detect_stages(frame, stage_counts)
        for s, dets in by_stage.items():
            st = stats[s]
            matched = set()
            found_fpr = set()
            for det in dets:
                cands = [(np.linalg.norm(det.T_cam_obj[:3, 3] - t["T_cam_obj"][:3, 3]), j)
                         for j, t in enumerate(truths) if t["cls"] == det.cls]
                ok = False
                if cands:
                    _, j = min(cands)
                    d = det.T_cam_obj[:3, 3] - truths[j]["T_cam_obj"][:3, 3]
                    ok = bool(np.all(np.abs(d) <= FALSE_POSITIVE_M))
                    if ok:
                        matched.add(j)
                        if det.fpr_pass:
                            found_fpr.add(j)
                st["dets"] += 1
                st["correct"] += ok
                st["dets_fpr"] += det.fpr_pass
                st["correct_fpr"] += ok and det.fpr_pass
                # what the belief-sum test gets to judge: detections the depth and colour checks let through
                if det.extra.get("depth_fit", {}).get("ok", True) and det.extra.get("colour", {}).get("pass", True):
                    records.append((det.cls, s, det.belief_sum, ok))
            for j, t in enumerate(truths):
                z = t["T_cam_obj"][2, 3]
                if not (near_far[0] <= z <= near_far[1] and t["visible"] >= min_visible):
                    continue
                if not np.all((t["keypoints_px"][8] >= 0) & (t["keypoints_px"][8] < [frame.info.width, frame.info.height])):
                    continue
                st["instances"] += 1
                best = None
                for det in dets:
                    if det.cls != t["cls"]:
                        continue
                    e = float(np.linalg.norm(det.T_cam_obj[:3, 3] - t["T_cam_obj"][:3, 3]))
                    if best is None or e < best[0]:
                        best = (e, det)
                if best is not None and j in matched:
                    st["found"] += 1
                    st["found_fpr"] += j in found_fpr
                if best is not None and best[0] < 0.25:
                    st["pos_err"].append(best[0])
                    dims = detector.dims[t["cls"]]
                    st["add_pass"] += add_error(best[1].T_cam_obj, t["T_cam_obj"], dims) < 0.1 * np.linalg.norm(dims)
    out = {}
    for s, st in stats.items():
        n = max(st["instances"], 1)
        out[str(s)] = {
            "instances": st["instances"],
            "detection_rate": st["found"] / n,
            "detection_rate_fpr": st["found_fpr"] / n,
            "median_position_error_m": float(np.median(st["pos_err"])) if st["pos_err"] else None,
            "add_pass_rate": st["add_pass"] / n,
            "predictions": st["dets"], "precision": st["correct"] / max(st["dets"], 1),
            "predictions_fpr": st["dets_fpr"], "precision_fpr": st["correct_fpr"] / max(st["dets_fpr"], 1),
        }
    return {"per_stages": out, "records": records, "images": len(frames)}
