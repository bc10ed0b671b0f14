"""Regression baselines: each cell's metrics compared with an earlier ``dopeslam test`` output
(its ``summary.json``); a change for the worse beyond the metric's tolerance fails.

Defaults below (direction: +1 higher is better, -1 lower is better; tolerance in the metric's
unit); a suite's ``[baseline_tolerance]`` table overrides a tolerance. Paths a case expects on are
compared too, their direction from the comparison (``>=`` higher is better, ``<=`` lower).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from stack.errors import DopeSlamError
from stack.io import read_user_text
from testbed.testing.expect import lookup

RUN_METRICS = {  # path: (direction, tolerance)
    "labels_summary.correct_labels": (+1, 0.0),
    "labels_summary.false_labels": (-1, 0.0),
    "labels_summary.map_precision": (+1, 0.05),
    "labels_summary.mean_error_m": (-1, 0.01),
    "odometry.ate_rmse_m": (-1, 0.01),
    "detection.precision": (+1, 0.05),
}
NAVIGATE_METRICS = {"success": (+1, 0.0), "final_distance_m": (-1, 0.10)}
_DIRECTION = {">=": +1, ">": +1, "<=": -1, "<": -1}


class BaselineError(DopeSlamError, ValueError):
    """A baseline folder that cannot be read (one line)."""


def metric_table(case) -> dict[str, tuple[int, float]]:
    table = dict(NAVIGATE_METRICS if case.options.get("job") == "navigate" else RUN_METRICS)
    for e in case.expectations:
        if e.path not in table and e.op in _DIRECTION:
            table[e.path] = (_DIRECTION[e.op], 0.0)
    return table


def metrics_of(report: dict, case) -> dict:
    out = {}
    for path in metric_table(case):
        try:
            v = lookup(report, path)
        except KeyError:
            continue
        out[path] = float(v) if isinstance(v, (int, float)) and math.isfinite(float(v)) else None
    return out


def load_baseline(folder: str | Path) -> dict:
    path = Path(folder) / "summary.json"
    if not path.exists():
        raise BaselineError(f"--baseline {folder}: no summary.json there (write one with --update-baseline)")
    text = read_user_text(path, BaselineError, "a dopeslam test summary (JSON)")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise BaselineError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(data, dict) or not isinstance(data.get("cases"), list):
        raise BaselineError(f"{path}: expected a dopeslam test summary (a 'cases' list)")
    return data


def _index(summary: dict) -> dict[tuple[str, int], dict]:
    return {(c["id"], cell["seed"]): cell.get("metrics", {}) for c in summary["cases"] for cell in c.get("cells", [])}


def compare(summary: dict, baseline: dict, tolerances: dict | None = None, cases=None) -> list[dict]:
    """Annotate every cell of ``summary`` with ``deltas`` against ``baseline``; returns the
    regressions ({case, seed, path, baseline, measured, delta, tolerance}). ``cases``: the plan's
    cases (for each metric's direction), by id."""
    tolerances = tolerances or {}
    old = _index(baseline)
    regressions = []
    by_id = {c.id: c for c in (cases or [])}
    for case in summary["cases"]:
        table = metric_table(by_id[case["id"]]) if case["id"] in by_id else {**RUN_METRICS, **NAVIGATE_METRICS}
        for cell in case["cells"]:
            before = old.get((case["id"], cell["seed"]))
            cell["deltas"] = {}
            if before is None:
                continue
            for path, now in cell.get("metrics", {}).items():
                was = before.get(path)
                if was is None or path not in table:
                    continue
                direction, tol = table[path]
                tol = tolerances.get(path, tol)
                delta = None if now is None else now - was
                worse = now is None or direction * delta < -tol - 1e-12
                cell["deltas"][path] = {"baseline": was, "delta": delta, "tolerance": tol, "regression": worse}
                if worse:
                    regressions.append({"case": case["id"], "seed": cell["seed"], "path": path, "baseline": was,
                                        "measured": now, "delta": delta, "tolerance": tol})
                    cell["passed"] = False
        if any(c["deltas"].get(p, {}).get("regression") for c in case["cells"] for p in c.get("deltas", {})):
            case["passed"] = False
    return regressions


def regression_message(r: dict) -> str:
    if r["measured"] is None:
        return f"{r['path']}: no value now, baseline {r['baseline']:.4g}"
    return (f"{r['path']}: {r['measured']:.4g}, baseline {r['baseline']:.4g} (change {r['delta']:+.4g}, "
            f"tolerance {r['tolerance']:.4g})")
