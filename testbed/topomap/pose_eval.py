"""Monocular pose estimation on the bundled scenarios' camera streams: ORPE vs Grunert (P3P) vs TRPE,
as in the topological-map paper's section 4.2.

* Span: from the first image where the robot moves, ``SPANS[scenario]`` images (the seed used KITTI
  frames 40-120); the whole moving part is also run once per method to say where each loses track.
* Initialisation: the first and the 20th image of the span with the true distance between them
  (the paper's "given baseline").
* Table 2 (without bundle adjustment): ``--runs`` runs per method with different RANSAC seeds on
  the same images; a run fails when five consecutive images get no pose; the absolute error is
  the distance between the last true and the last estimated camera position (world, with the
  first key frame's true pose as the map's origin).
* Figures 15-18 and Table 3 (with local bundle adjustment over six key frames, the last two
  optimised): rotation and translation error along the path length, the trajectory in the plane,
  the camera height, time per image (features + matching + pose; bundle adjustment included).

Features (corners + descriptors) are computed once per image and cached beside the stream.

    dopeslam pose-eval [--scenarios experiment3_columns,shelf_corridor] [--runs 100] --out out/topomap/pose
"""
from __future__ import annotations

import hashlib
import logging
import math
import time
from pathlib import Path

import numpy as np

from stack.topomap.mono_pose import METHODS, Features, MonoConfig, detect_features
from stack.topomap.mono_vo import run_sequence
from testbed.topomap import InputError, print_saved_report
from testbed.topomap.stream import CameraStream, cache_root, camera_stream

log = logging.getLogger(__name__)
SPANS = {"experiment3_columns": 150, "shelf_corridor": 80}
DEFAULT_SCENARIOS = ("experiment3_columns", "shelf_corridor")
INIT_GAP = 20
LABELS = {"orpe": "ORPE", "trpe": "TRPE", "grunert": "Grunert P3P"}
COLOURS = {"orpe": "tab:red", "trpe": "tab:blue", "grunert": "tab:green"}


def stream_features(stream: CameraStream, cfg: MonoConfig, indices: np.ndarray) -> tuple[list[Features], np.ndarray]:
    """Features of the given images (cached on disk by stream and feature settings) and the seconds each took."""
    fcfg = (cfg.max_corners, cfg.corner_quality, cfg.corner_min_distance, cfg.blur_sigma, cfg.min_eigenvalue, cfg.sift_size)
    key = hashlib.sha1(f"{stream.scenario}/{stream.seed}/{stream.light}/{stream.info.width}/{fcfg}".encode()).hexdigest()[:10]
    path = cache_root() / f"features_{stream.scenario}_{key}.npz"
    cached = {}
    if path.exists():
        z = np.load(path)
        for i in z["indices"]:
            cached[int(i)] = (Features(z[f"uv{i}"], z[f"desc{i}"]), float(z[f"sec{i}"]))
    feats, secs = [], []
    new = False
    for n, i in enumerate(indices):
        if int(i) not in cached:
            t0 = time.perf_counter()
            f = detect_features(stream.gray(int(i)), cfg)
            cached[int(i)] = (f, time.perf_counter() - t0)
            new = True
            if n % 50 == 0:
                log.info("features of %s: image %d / %d", stream.scenario, n + 1, len(indices))
        feats.append(cached[int(i)][0])
        secs.append(cached[int(i)][1])
    if new:
        arrays = {"indices": np.array(sorted(cached))}
        for i, (f, s) in cached.items():
            arrays[f"uv{i}"] = f.uv
            arrays[f"desc{i}"] = f.desc
            arrays[f"sec{i}"] = np.array(s)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **arrays)
        tmp.replace(path)
    return feats, np.array(secs)


def _rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return math.degrees(math.acos(float(np.clip(c, -1, 1))))


def errors_along_path(vo, T_gt: np.ndarray) -> dict:
    """Per tracked image: path length travelled (true), rotation error (deg), translation error (m)."""
    T0 = T_gt[0]
    steps = np.r_[0.0, np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1)]
    path = np.cumsum(steps)
    rows = []
    for r in vo.results:
        if not r.ok:
            continue
        est = T0 @ r.T_world_camera
        gt = T_gt[r.index]
        rows.append((r.index, path[r.index], _rot_err_deg(est[:3, :3], gt[:3, :3]),
                     float(np.linalg.norm(est[:3, 3] - gt[:3, 3])), *est[:3, 3], *gt[:3, 3]))
    a = np.array(rows).reshape(-1, 10)
    return {"index": a[:, 0].astype(int), "path_m": a[:, 1], "rot_deg": a[:, 2], "trans_m": a[:, 3],
            "est_xyz": a[:, 4:7], "gt_xyz": a[:, 7:10]}


def run_once(feats, secs, stamps, T_gt, K, size, method, seed, ba: bool, cfg: MonoConfig) -> dict:
    c = MonoConfig(**{**cfg.__dict__, "ba": ba})
    baseline = float(np.linalg.norm(T_gt[INIT_GAP, :3, 3] - T_gt[0, :3, 3]))
    t0 = time.perf_counter()
    vo = run_sequence(None, stamps, K, size, method, baseline, seed=seed, cfg=c, init_gap=INIT_GAP, features=feats)
    wall = time.perf_counter() - t0
    processed = len(vo.results)
    last_ok = max((r.index for r in vo.results if r.ok), default=None)
    out = {"failed": bool(vo.failed), "images": len(stamps), "processed": processed,
           "tracked": sum(r.ok for r in vo.results), "last_tracked_index": last_ok, "keyframes": len(vo.keyframes),
           "points": len(vo.points),
           # time per image: features + matching + pose (+ bundle adjustment); initialisation spread over the span
           "seconds_per_image": (wall + float(np.sum(secs[:INIT_GAP + 1 + processed]))) / max(1, processed + INIT_GAP + 1),
           "ba_seconds": vo.ba_seconds}
    if last_ok is not None:
        e = errors_along_path(vo, T_gt)
        out["absolute_error_m"] = float(e["trans_m"][-1])
        out["mean_translation_error_m"] = float(np.mean(e["trans_m"]))
        out["mean_rotation_error_deg"] = float(np.mean(e["rot_deg"]))
        out["path_m"] = float(e["path_m"][-1])
        out["_errors"] = e
    return out


def evaluate_scenario(name: str, runs: int, cfg: MonoConfig, span: int | None = None) -> dict:
    stream = camera_stream(name)
    a, b = stream.moving_range()
    span = span or SPANS.get(name, 120)
    full = np.arange(a, b + 1)
    idx = full[:span]
    feats_full, secs_full = stream_features(stream, cfg, full)
    K, size = stream.info.K, (stream.info.width, stream.info.height)
    T_full = stream.T_world_camera[full]
    res = {"scenario": name, "span": {"first_image": int(idx[0]), "last_image": int(idx[-1]), "images": len(idx),
                                      "path_m": float(np.sum(np.linalg.norm(np.diff(T_full[:len(idx), :3, 3], axis=0), axis=1)))},
           "moving_images": len(full), "methods": {}}
    for m in METHODS:
        log.info("%s: %s, %d runs without bundle adjustment", name, m, runs)
        table = []
        t0 = time.perf_counter()
        for seed in range(runs):
            r = run_once(feats_full[:len(idx)], secs_full[:len(idx)], stream.stamps[idx], T_full[:len(idx)], K, size,
                         m, seed, False, cfg)
            r.pop("_errors", None)
            table.append(r)
            if time.perf_counter() - t0 > 60:
                t0 = time.perf_counter()
                log.info("%s %s: run %d / %d", name, m, seed + 1, runs)
        ok = [r for r in table if not r["failed"]]
        abs_err = [r["absolute_error_m"] for r in ok if "absolute_error_m" in r]
        res["methods"][m] = {
            "table2": {"runs": runs, "failures": runs - len(ok),
                       "absolute_error_m_mean": float(np.mean(abs_err)) if abs_err else None,
                       "absolute_error_m_median": float(np.median(abs_err)) if abs_err else None,
                       "absolute_error_m_max": float(np.max(abs_err)) if abs_err else None,
                       "mean_translation_error_m": float(np.mean([r["mean_translation_error_m"] for r in ok])) if ok else None,
                       "mean_rotation_error_deg": float(np.mean([r["mean_rotation_error_deg"] for r in ok])) if ok else None,
                       "seconds_per_image": float(np.mean([r["seconds_per_image"] for r in table]))},
        }
        # one run with bundle adjustment over the span, and one over the whole moving part
        r_ba = run_once(feats_full[:len(idx)], secs_full[:len(idx)], stream.stamps[idx], T_full[:len(idx)], K, size,
                        m, 0, True, cfg)
        r_full = run_once(feats_full, secs_full, stream.stamps[full], T_full, K, size, m, 0, True, cfg)
        e = r_ba.pop("_errors", None)
        r_full.pop("_errors", None)
        res["methods"][m]["with_ba"] = r_ba
        res["methods"][m]["whole_drive_with_ba"] = {k: r_full[k] for k in ("failed", "images", "tracked", "last_tracked_index",
                                                                          "path_m", "absolute_error_m") if k in r_full}
        if e is not None:
            res["methods"][m]["_curve"] = e
    return res


def plot_scenario(res: dict, out: Path) -> None:
    from testbed.plots import plt, save

    name = res["scenario"]
    curves = {m: r["_curve"] for m, r in res["methods"].items() if "_curve" in r}
    for key, what, unit, fig_name in (("rot_deg", "rotation", "deg", "fig15_rotation"),
                                      ("trans_m", "translation", "m", "fig16_translation")):
        fig, ax = plt.subplots(figsize=(7, 3.6))
        for m, e in curves.items():
            ax.plot(e["path_m"], e[key], "-", color=COLOURS[m], label=LABELS[m])
        ax.set_xlabel("path length (m)")
        ax.set_ylabel(f"{what} error ({unit})")
        ax.set_title(f"{name}: {what} error along the path (with local BA)", fontsize=9)
        ax.legend(fontsize=8)
        save(fig, out / f"{fig_name}_{name}.png")
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [2, 1]})
    first = next(iter(curves.values()), None)
    if first is not None:
        ax.plot(first["gt_xyz"][:, 0], first["gt_xyz"][:, 1], "k-", lw=2, label="ground truth")
    for m, e in curves.items():
        ax.plot(e["est_xyz"][:, 0], e["est_xyz"][:, 1], "-", color=COLOURS[m], label=LABELS[m])
        ax2.plot(e["path_m"], e["est_xyz"][:, 2], "-", color=COLOURS[m], label=LABELS[m])
    if first is not None:
        ax2.plot(first["path_m"], first["gt_xyz"][:, 2], "k-", lw=2, label="ground truth")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.set_title(f"{name}: camera trajectory (fig. 17)", fontsize=9)
    ax.legend(fontsize=8)
    ax2.set_xlabel("path length (m)")
    ax2.set_ylabel("camera height (m)")
    ax2.set_title("camera height (fig. 18)", fontsize=9)
    save(fig, out / f"fig17_trajectory_{name}.png")


def run(scenarios=DEFAULT_SCENARIOS, runs: int = 100, out: Path = Path("out/topomap/pose")) -> dict:
    from testbed.io import write_json

    out.mkdir(parents=True, exist_ok=True)
    cfg = MonoConfig()
    report = {"config": cfg.__dict__, "init_gap_images": INIT_GAP, "scenarios": {}}
    for name in scenarios:
        res = evaluate_scenario(name, runs, cfg)
        plot_scenario(res, out)
        for m in res["methods"].values():
            m.pop("_curve", None)
        report["scenarios"][name] = res
        write_json(out / "pose_eval.json", report)
    return report


def print_tables(report: dict) -> None:
    for name, res in report["scenarios"].items():
        sp = res["span"]
        print(f"{name}: images {sp['first_image']}-{sp['last_image']} ({sp['images']}, {sp['path_m']:.2f} m)")
        print(f"  {'method':<12} {'failures':>9} {'abs err m':>10} {'mean t err':>10} {'mean R err':>10} "
              f"{'| BA abs err':>12} {'ms/image':>9} {'| whole drive: tracked':>23}")
        for m, r in res["methods"].items():
            t2, ba, wd = r["table2"], r["with_ba"], r["whole_drive_with_ba"]
            f = lambda v, s=1.0, d=3: "-" if v is None else f"{v * s:.{d}f}"  # noqa: E731
            print(f"  {LABELS[m]:<12} {t2['failures']:>5}/{t2['runs']:<3} {f(t2['absolute_error_m_median']):>10} "
                  f"{f(t2['mean_translation_error_m']):>10} {f(t2['mean_rotation_error_deg'], 1, 2):>10} "
                  f"{f(ba.get('absolute_error_m')) + ('*' if ba['failed'] else ''):>12} {1000 * ba['seconds_per_image']:>9.0f} "
                  f"{wd['tracked']:>12}/{wd['images'] - INIT_GAP - 1} images, {wd.get('path_m', 0):.1f} m")
        print("  (* the run lost track: its error is at the last tracked image)")


def run_args(args) -> int:
    """``dopeslam pose-eval`` (options: ``testbed/commands/topomap.py``)."""
    if args.table is not None:
        print_saved_report(args.table, f"--table {args.table}", "a pose_eval.json", print_tables)
        return 0
    if args.runs < 1:
        raise InputError(f"--runs: expected at least 1 RANSAC seed per method, got {args.runs}")
    report = run(args.scenarios.split(","), args.runs, args.out)
    print_tables(report)
    print(f"wrote {args.out}/pose_eval.json and fig15-17 PNGs")
    return 0
