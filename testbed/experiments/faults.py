"""``dopeslam experiment faults --out DIR``: each sensor fault swept over its rate on a scenario
(default: the default scenario), one episode per rate: labels in the map, false labels, mean label
error and LiDAR odometry ATE against the rate, as ``faults.json`` and one PNG per fault.

Every episode uses the same seed, so the only thing that changes along a curve is the fault (its
own random stream derives from the seed too). ``--duration`` keeps the sweep short; the faults and
rates are configurable (``faults={"lidar_drop": (0, 0.2, 0.5)}``).
"""
from __future__ import annotations

import logging
from pathlib import Path

from testbed.experiments import EPISODE_APPLIES

log = logging.getLogger(__name__)

# fault -> the rates swept (the first is the fault-free value)
SWEEP = {
    "lidar_drop": (0.0, 0.2, 0.5),
    "partial_sweep": (0.0, 0.3, 0.7),
    "camera_drop": (0.0, 0.2, 0.5),
    "camera_latency": (0.0, 0.05, 0.2),
    "camera_late_stamp": (0.0, 0.05, 0.2),
    "camera_clock_offset": (0.0, 0.05, 0.2),
    "depth_holes": (0.0, 0.1, 0.3),
    "motion_blur": (0.0, 0.01, 0.03),
    "exposure": (1.0, 0.5, 2.0),
    "flicker": (0.0, 0.3, 0.6),
    "wheel_slip": (0.0, 0.1, 0.3),
}
APPLIES = EPISODE_APPLIES  # the config it honours (docs/configuration.md)


def run(out_dir, scenario=None, seed: int | None = 0, duration: float | None = None, faults=None,
        stages=6, input_mode="rgb", weights=None, detector=None, config=None) -> dict:
    """One episode per (fault, rate); the fault-free episode is run once and shared by every curve.
    ``config``: a ``testbed.settings.RunConfig`` whose :data:`APPLIES` sections replace the shipped stack's."""
    from testbed.experiments import episode_config
    from testbed.io import write_json
    from testbed.progress import runs
    from testbed.run import run_episode

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sweep = {k: tuple(v) for k, v in (faults or SWEEP).items()}
    cache: dict[tuple, dict] = {}
    result = {"scenario": scenario or "experiment3_columns", "seed": seed, "duration_s": duration, "faults": {}}
    pairs = [(name, rate) for name, rates in sweep.items() for rate in rates]
    rows: dict[str, list] = {}
    for name, rate in runs(pairs, "faults", unit="setting"):
        clean = rate == SWEEP.get(name, (0.0,))[0]
        key = ("clean",) if clean else (name, rate)
        if key not in cache:
            log.info("faults: %s = %s", name, rate)
            rep = run_episode(scenario, out / "runs" / (f"{name}_{rate:g}" if not clean else "clean"), seed,
                              input_mode=input_mode, stages=stages, weights=weights, duration=duration,
                              detector=detector, faults=() if clean else (f"{name}={rate}",),
                              config=episode_config(config, input_mode, stages, weights))
            s = rep["labels_summary"]
            cache[key] = {"labels": s["labels_in_map"], "correct": s["correct_labels"],
                          "false_labels": s["false_labels"], "objects": s["objects"],
                          "mean_error_m": s["mean_error_m"], "ate_rmse_m": rep["odometry"]["ate_rmse_m"],
                          "stale_labels": s.get("stale_labels", 0),
                          "fault_counts": (rep.get("faults") or {}).get("counts")}
        rows.setdefault(name, []).append({"rate": rate, **cache[key]})
        if len(rows[name]) == len(sweep[name]):  # the fault's curve is complete
            result["faults"][name] = rows[name]
            _plot(out / f"fault_{name}.png", name, rows[name], result)
            write_json(out / "faults.json", result)
    return result


def _plot(path: Path, name: str, rows: list[dict], result: dict) -> None:
    from testbed.plots import plt, save

    x = [r["rate"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    a.plot(x, [r["correct"] for r in rows], "o-", label="correct labels")
    a.plot(x, [r["false_labels"] for r in rows], "s-", color="red", label="false labels")
    a.axhline(rows[0]["objects"], color="0.6", lw=0.8, ls=":", label="objects")
    a.set_xlabel(name)
    a.set_ylabel("labels")
    a.legend(fontsize=7)
    b.plot(x, [100 * (r["mean_error_m"] or float("nan")) for r in rows], "o-", label="mean label error")
    b.plot(x, [100 * r["ate_rmse_m"] for r in rows], "^-", color="green", label="odometry ATE")
    b.set_xlabel(name)
    b.set_ylabel("cm")
    b.legend(fontsize=7)
    dur = result["duration_s"]
    fig.suptitle(f"{result['scenario']} seed {result['seed']}{'' if dur is None else f', {dur:g} s'}: {name}",
                 fontsize=9)
    save(fig, path)


def table(result: dict) -> str:
    lines = [f"{'fault':<20} {'rate':>6} {'correct':>8} {'false':>6} {'error cm':>9} {'ATE cm':>7}"]
    for name, rows in result["faults"].items():
        for r in rows:
            err = "-" if r["mean_error_m"] is None else f"{100 * r['mean_error_m']:.1f}"
            lines.append(f"{name:<20} {r['rate']:>6g} {r['correct']:>4}/{r['objects']:<3} {r['false_labels']:>6} "
                         f"{err:>9} {100 * r['ate_rmse_m']:>7.1f}")
    return "\n".join(lines)


def parse_faults_option(text: str) -> dict:
    """``lidar_drop=0,0.2,0.5;camera_drop=0,0.5`` -> {name: rates}; ValueError names the bad part."""
    from sim.faults import Faults

    out = {}
    for part in filter(None, (p.strip() for p in text.split(";"))):
        name, sep, rates = part.partition("=")
        if not sep or name.strip() not in Faults.model_fields:
            raise ValueError(f"{part!r}: expected NAME=RATE,RATE,... with NAME one of {sorted(Faults.model_fields)}")
        try:
            out[name.strip()] = tuple(float(v) for v in rates.split(","))
        except ValueError:
            raise ValueError(f"{part!r}: expected comma-separated numbers") from None
        Faults(**{name.strip(): max(out[name.strip()], key=abs)})  # in range (raises ValidationError)
    return out

