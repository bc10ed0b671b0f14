"""Experiment 1 of the paper (sections 4.2, 5.1): DOPE's depth estimate of the "E" object at five
points of a grid on the floor plane (x in [-30, 30] cm, z up to 170 cm from the colour lens, the
height held constant). Per point: dx, dz (detected - truth), eq. 6 distance sqrt(dx^2 + dz^2) and
eq. 7 accuracy 1 - | |T| - |D| | / |T|, from the median of the frames' detections.

The paper gives no coordinates for its five points; ours (``GRID_CM``) span the same area.

Each frame's E detection is the one with the highest mean key-point peak among those the depth image
supports (the detector's depth check); the belief-sum FPR threshold is not applied here (experiment 2
measures it). Two estimates are scored from the same detections: the stack's pose (PnP, then fitted
along the viewing ray to the depth image) and the PnP-only pose, which is what the paper's RGB DOPE
gives (``pnp_only`` in the JSON)."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from stack.metrics import paper_accuracy, paper_distance_xz
from testbed.experiments.localization import PAPER
from testbed.io import write_json

log = logging.getLogger(__name__)
GRID_CM = {"P1": (-30.0, 60.0), "P2": (30.0, 80.0), "P3": (0.0, 110.0), "P4": (-25.0, 140.0), "P5": (20.0, 170.0)}
KEYS = ("dx_cm", "dz_cm", "distance_cm", "accuracy_pct")


APPLIES = {"detector"}  # the config it honours (docs/configuration.md)


def run(out_dir, weights=None, stages=6, frames=10, seed=0, input_mode="rgb", config=None) -> dict:
    """``config``: a ``testbed.settings.RunConfig`` whose [detector] settings replace the shipped
    detector's (input, stages and weights are this experiment's; every belief sum passes FPR)."""
    from sim.objects import load_catalog
    from stack.dope_fpr import DopeDetector, FprThresholds
    from testbed.experiments.static_rig import StaticRig
    from testbed.progress import bar

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dims = {c: s.dims for c, s in load_catalog().items()}
    settings = {} if config is None else config.detector.dope_kwargs()
    det = DopeDetector(**{**settings, "weights": weights, "input": input_mode, "stages": stages, "fpr": True},
                       dims=dims, thresholds=FprThresholds())  # belief sums all pass; the depth check stays
    result = {"weights": str(det.weights_path), "weights_meta": _meta(det), "stages": stages, "frames_per_point": frames,
              "input": input_mode, "grid_cm": GRID_CM}
    rows, pnp_rows = {}, {}
    with StaticRig("E", seed=seed) as rig, bar(len(GRID_CM) * frames, "depth grid", unit="frame") as progress:
        for name, (x_cm, z_cm) in GRID_CM.items():
            T_cam_obj = rig.place(x_cm / 100, z_cm / 100)
            truth = T_cam_obj[:3, 3]
            found, found_pnp = [], []
            for _ in range(frames):
                dets = [d for d in det.detect(rig.frame()) if d.cls == "E" and d.fpr_pass]
                progress.update(1)
                if dets:
                    best = max(dets, key=lambda d: float(np.mean(d.peak_scores)))
                    found.append(best.T_cam_obj[:3, 3])
                    found_pnp.append(best.extra.get("pnp_pose", best.T_cam_obj)[:3, 3])
            rows[name] = _score_point(x_cm, z_cm, truth, found, frames)
            pnp_rows[name] = _score_point(x_cm, z_cm, truth, found_pnp, frames)
            log.info("%s (%+.0f, %.0f) cm: %d/%d frames, distance %s cm (PnP only %s cm)", name, x_cm, z_cm,
                     len(found), frames, rows[name]["distance_cm"], pnp_rows[name]["distance_cm"])
    rows["avg"] = _average(rows)
    pnp_rows["avg"] = _average(pnp_rows)
    result["pnp_only"] = pnp_rows
    result.update(rows)
    result["paper"] = _paper()
    write_json(out / "depth_grid.json", result)
    (out / "depth_grid_table.txt").write_text(table(result) + "\n")
    return result


def _score_point(x_cm, z_cm, truth, found, frames) -> dict:
    row = {"x_cm": x_cm, "z_cm": z_cm, "detected_frames": len(found), "frames": frames}
    if found:
        d = np.median(np.array(found), axis=0)
        row.update({"dx_cm": 100 * float(d[0] - truth[0]), "dz_cm": 100 * float(d[2] - truth[2]),
                    "distance_cm": 100 * paper_distance_xz(truth, d), "accuracy_pct": 100 * paper_accuracy(truth, d)})
    else:
        row.update({k: None for k in KEYS})
    return row


def _average(rows: dict) -> dict:
    ok = [r for r in rows.values() if r["distance_cm"] is not None]
    avg = {k: (float(np.mean([r[k] for r in ok])) if ok else None) for k in KEYS}
    avg["detected_points"] = len(ok)
    return avg


def _meta(det) -> dict:
    extra = getattr(det, "weights_extra", None) or {}
    return {k: extra[k] for k in ("images", "steps", "train_images", "data_images") if k in extra}


def _paper() -> dict | None:
    try:
        return json.loads(PAPER.read_text())["experiment_1_depth_grid"]["datasets"]
    except (OSError, KeyError, ValueError):
        return None


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.1f}"


def table(result) -> str:
    paper = result.get("paper") or {}
    best = paper.get("100k", {})
    lines = [f"weights: {result['weights']} {result.get('weights_meta') or ''}",
             f"{'point':<5} {'x,z cm':>10} {'found':>6} " + " ".join(f"{k:>12}" for k in KEYS) +
             "   paper 100k (dx dz dist acc)"]
    for title, rows in (("stack (PnP + depth fit)", result), ("PnP only (the paper's RGB DOPE)", result.get("pnp_only"))):
        if rows is None:
            continue
        lines.append(title + ":")
        for name in list(GRID_CM) + ["avg"]:
            r = rows[name]
            where = f"{r['x_cm']:+.0f},{r['z_cm']:.0f}" if name != "avg" else ""
            found = f"{r['detected_frames']}/{r['frames']}" if name != "avg" else f"{r['detected_points']}/5"
            ref = " ".join(str(v) for v in best.get(name, []))
            lines.append(f"{name:<5} {where:>10} {found:>6} " + " ".join(f"{_fmt(r[k]):>12}" for k in KEYS) + f"   {ref}")
    return "\n".join(lines)
