"""Experiment 2 of the paper (sections 4.3, 5.2): precision, recall and F-score of DOPE with and
without FPR at 1..6 stages. The "E" object stands static 80 cm from the camera in complete darkness;
DOPE gets the depth map sliced to a 30 cm window. A prediction more than 5 cm from the truth in any
axis is a false positive; TP = predictions, CP = TP - FP, TI = frames (the object is in every frame):
precision = CP / TP, recall = CP / TI, F = 2 CP / (TP + TI) (eq. 3-5).

Configurations D(i, j): i stages, j = F (FPR on) or 0 (off). Each run renders its frames once (its own
seed: sensor noise) and evaluates every stage count from one forward pass; the frame rate of each
stage count is timed separately on the same frames."""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from stack.metrics import is_false_positive, precision_recall_f
from testbed.experiments.localization import PAPER
from testbed.io import write_json

log = logging.getLogger(__name__)
DISTANCE_M = 0.80
WINDOW_M = 0.30
CAMERA_HZ = 10.0


def configs():
    return [f"D{i}{j}" for i in range(1, 7) for j in ("F", "0")]


APPLIES = {"detector"}  # the config it honours (docs/configuration.md)


def run(out_dir, runs=5, seconds=60.0, weights=None, input_mode="depth", seed=0, timing_frames=10,
        config=None) -> dict:
    """``config``: a ``testbed.settings.RunConfig`` whose [detector] settings replace the shipped
    detector's (input and weights are this experiment's; six stages; one depth window at the object)."""
    from sim.objects import load_catalog
    from stack.dope_fpr import DopeDetector
    from testbed.experiments.static_rig import StaticRig
    from testbed.progress import bar

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dims = {c: s.dims for c, s in load_catalog().items()}
    window = [(DISTANCE_M - WINDOW_M / 2, DISTANCE_M + WINDOW_M / 2)]
    settings = {} if config is None else config.detector.dope_kwargs()
    det = DopeDetector(**{**settings, "weights": weights, "input": input_mode, "stages": 6, "fpr": True,
                          "depth_windows": window}, dims=dims)
    n_frames = max(1, int(round(seconds * CAMERA_HZ)))
    per_run = {c: [] for c in configs()}
    progress = bar(runs * (n_frames + min(timing_frames, n_frames) * 6), "precision", unit="frame")
    for r in range(runs):
        counts = {c: {"tp": 0, "fp": 0} for c in configs()}
        fps = {}
        with StaticRig("E", seed=seed + r, light=0.0) as rig:
            truth = rig.place(0.0, DISTANCE_M)[:3, 3]
            frames = [rig.frame() for _ in range(n_frames)]
        for i, frame in enumerate(frames):
            by_stage = det.detect_stages(frame, range(1, 7))
            progress.update(1)
            for s, dets in by_stage.items():
                for d in dets:
                    if d.cls != "E":
                        continue
                    fp = is_false_positive(truth, d.T_cam_obj[:3, 3], 0.05)
                    for j, passes in (("0", True), ("F", d.fpr_pass)):
                        if passes:
                            counts[f"D{s}{j}"]["tp"] += 1
                            counts[f"D{s}{j}"]["fp"] += int(fp)
            if (i + 1) % 100 == 0:
                log.info("run %d/%d: %d/%d frames", r + 1, runs, i + 1, n_frames)
        for s in range(1, 7):  # frame rate of each stage count, timed on the run's own frames
            det.stages = s
            sample = frames[:timing_frames]
            t0 = time.perf_counter()
            for f in sample:
                det.detect(f)
            progress.update(len(sample))
            fps[s] = len(sample) / (time.perf_counter() - t0)
        det.stages = 6
        for c, v in counts.items():
            pr = precision_recall_f(v["tp"], v["fp"], n_frames)
            per_run[c].append({"precision": pr.precision, "recall": pr.recall, "f_score": pr.f_score,
                               "fps": fps[int(c[1])], "tp": v["tp"], "fp": v["fp"], "ti": n_frames})
        log.info("run %d/%d done: D6F precision %.3f recall %.3f", r + 1, runs, per_run["D6F"][-1]["precision"],
                 per_run["D6F"][-1]["recall"])
    progress.close()
    result = {"setup": {"distance_m": DISTANCE_M, "window_m": WINDOW_M, "light": 0.0, "input": input_mode,
                        "runs": runs, "seconds": seconds, "frames_per_run": n_frames, "weights": str(det.weights_path),
                        "false_positive_m": 0.05}}
    for c, rs in per_run.items():
        entry = {}
        for k in ("precision", "recall", "f_score", "fps"):
            vals = np.array([x[k] for x in rs], dtype=float)
            entry[k] = float(np.nanmean(vals)) if np.any(np.isfinite(vals)) else None
            entry[f"{k}_min"] = float(np.nanmin(vals)) if np.any(np.isfinite(vals)) else None
            entry[f"{k}_max"] = float(np.nanmax(vals)) if np.any(np.isfinite(vals)) else None
        entry["runs"] = rs
        result[c] = entry
    result["speedup_1_vs_6"] = result["D1F"]["fps"] / result["D6F"]["fps"]
    result["paper"] = _paper()
    write_json(out / "precision.json", result)
    (out / "precision_table.txt").write_text(table(result) + "\n")
    plot(result, out)
    return result


def _paper():
    try:
        return json.loads(PAPER.read_text())["experiment_2_precision"]
    except (OSError, KeyError, ValueError):
        return None


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def table(result) -> str:
    paper = result.get("paper") or {}
    pp, pr, pf = paper.get("precision_pct", {}), paper.get("recall_pct", {}), paper.get("frame_rate_hz", {})
    lines = [f"{'config':<6} {'precision %':>12} {'(min-max)':>13} {'recall %':>9} {'F %':>6} {'fps':>6}   "
             f"{'paper P %':>9} {'paper R %':>9} {'paper Hz':>8}"]
    for c in configs():
        r = result[c]
        rng = f"({_pct(r['precision_min'])}-{_pct(r['precision_max'])})"
        lines.append(f"{c:<6} {_pct(r['precision']):>12} {rng:>13} {_pct(r['recall']):>9} {_pct(r['f_score']):>6} "
                     f"{r['fps'] or 0:>6.1f}   {str(pp.get(c, '-')):>9} {str(pr.get(c, '-')):>9} {str(pf.get(c, '-')):>8}")
    lines.append(f"1-vs-6-stage speed-up: {result['speedup_1_vs_6']:.2f}x (paper {paper.get('average_inference_speedup', '-')}x)")
    return "\n".join(lines)


def plot(result, out: Path) -> None:
    from testbed.plots import plt, save

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for j, marker, name in (("F", "o", "FPR"), ("0", "s", "no FPR")):
        for k, color in (("precision", "tab:blue"), ("recall", "tab:orange")):
            xs, ys, lo, hi = [], [], [], []
            for i in range(1, 7):
                r = result[f"D{i}{j}"]
                if r[k] is None:
                    continue
                xs.append(r["fps"])
                ys.append(100 * r[k])
                lo.append(100 * (r[k] - r[f"{k}_min"]))
                hi.append(100 * (r[f"{k}_max"] - r[k]))
            ax.errorbar(xs, ys, yerr=[lo, hi], fmt=marker + ("-" if j == "F" else "--"), color=color, capsize=3,
                        label=f"{k} ({name})")
    ax.set_xlabel("frame rate (Hz)")
    ax.set_ylabel("%")
    ax.set_title("Precision and recall vs frame rate (1..6 stages), cf. paper Fig. 6")
    ax.legend(fontsize=7)
    save(fig, out / "precision_recall_vs_fps.png")
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for j, marker, name in (("F", "o-", "FPR"), ("0", "s--", "no FPR")):
        pts = [(result[f"D{i}{j}"]["fps"], 100 * (result[f"D{i}{j}"]["f_score"] or 0)) for i in range(1, 7)]
        ax.plot(*zip(*pts), marker, label=name)
    ax.set_xlabel("frame rate (Hz)")
    ax.set_ylabel("F-score (%)")
    ax.set_title("F-score vs frame rate, cf. paper Fig. 7")
    ax.legend()
    save(fig, out / "fscore_vs_fps.png")
