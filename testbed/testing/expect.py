"""Expectations: ``"dotted.path" = "OP NUMBER"`` checked against a run's ``report.json``.

A path names a number in the report (``labels_summary.labelled``, ``odometry.ate_rmse_m``) or a
per-object field, ``labels.<object name>.<field>`` (``labels.Mustard.error_m``), where the object
is one of the scenario's. True/false values count as 1/0. ``min_pass_rate`` (0-1, default 1) is
the share of seeds on which every expectation must hold for the scenario to pass.
"""
from __future__ import annotations

import math
import operator
from dataclasses import asdict, dataclass

from sim.scenario import EXPECT_COMPARISON as _COMPARISON  # one syntax, checked where scenarios load
from stack.errors import DopeSlamError

OPS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt, "==": operator.eq,
       "!=": operator.ne}
PASS_RATE_KEY = "min_pass_rate"

# The numbers in the report of `dopeslam run` (testbed/run.py), by section.
RUN_KEYS = {
    "": {"sim_seconds", "wall_seconds", "real_time_factor", "light", "stages", "fpr"},
    "labels_summary": {"objects", "labels_in_map", "correct_labels", "false_labels", "misplaced", "phantom",
                       "map_precision", "map_recall", "labelled", "missing", "mean_error_m", "candidates"},
    "odometry": {"ate_rmse_m", "ate_rmse_umeyama_m", "rpe_trans_pct", "rpe_rot_deg_per_m", "poses",
                 "odometry_hz", "loop_closures", "loop_candidates_rejected", "false_loop_closures",
                 "ate_rmse_odometry_only_m"},
    "wheel_odometry": {"ate_rmse_m", "ate_rmse_umeyama_m", "rpe_trans_pct", "rpe_rot_deg_per_m", "poses"},
    "detection": {"frames", "predictions", "false_positives", "instances", "correct", "precision", "recall", "fps",
                  "detections_without_pose"},
    "time_split_s": {"simulation", "odometry", "dope", "fusion", "recording"},
}
LABEL_FIELDS = {"error_m", "false_label", "missing"}  # per object: labels.<object>.<field>
LOOP_CLOSURE_KEYS = {"loop_closures", "loop_candidates_rejected", "false_loop_closures", "ate_rmse_odometry_only_m"}
# The numbers in the report of `dopeslam navigate` (testbed/topomap/navigate.py, navigate.json).
NAVIGATE_KEYS = {"": {"success", "reached", "final_distance_m", "distance_to_object_m", "target_node_to_object_m",
                      "target_node_shows_object", "path_length_m", "sim_seconds", "wall_seconds"}}


class ExpectError(DopeSlamError, ValueError):
    """An expectation that cannot be used; the message names the key and what was expected."""


@dataclass(frozen=True)
class Expectation:
    path: str
    op: str
    bound: float

    def __str__(self) -> str:
        return f"{self.path} {self.op} {_fmt(self.bound)}"


@dataclass
class Outcome:
    path: str
    op: str
    bound: float
    measured: float | None
    ok: bool
    margin: float | None  # > 0: by how much it holds; < 0: by how much it misses
    note: str = ""

    def message(self) -> str:
        if self.measured is None:
            return f"{self.path}: expected {self.op} {_fmt(self.bound)}, measured nothing ({self.note})"
        return (f"{self.path}: measured {_fmt(self.measured)}, expected {self.op} {_fmt(self.bound)} "
                f"(margin {_fmt(self.margin)})")

    def as_dict(self) -> dict:
        return asdict(self)


def _fmt(v) -> str:
    if v is None:
        return "-"
    if float(v).is_integer() and abs(v) < 1e12:
        return str(int(v))
    return f"{v:.4g}"


def known_paths(job: str = "run") -> set[str]:
    keys = NAVIGATE_KEYS if job == "navigate" else RUN_KEYS
    return {f"{sec}.{k}" if sec else k for sec, ks in keys.items() for k in ks}


def parse_comparison(key: str, text) -> tuple[str, float]:
    """``">= 6"`` -> (">=", 6.0); a bare number or true/false means ``==``."""
    if isinstance(text, bool):
        return "==", float(text)
    if isinstance(text, (int, float)):
        return "==", float(text)
    m = _COMPARISON.match(text) if isinstance(text, str) else None
    if not m:
        raise ExpectError(f"expect '{key}': expected a comparison such as \">= 6\" or \"<= 0.05\" "
                          f"(one of {' '.join(OPS)} and a number), got {text!r}")
    op, num = m.groups()
    bound = {"true": 1.0, "false": 0.0}.get(num)
    bound = float(num) if bound is None else bound
    if not math.isfinite(bound):
        raise ExpectError(f"expect '{key}': expected a finite number, got {text!r}")
    return op, bound


def check_path(key: str, job: str = "run", objects: list[str] | None = None) -> None:
    if job == "run" and key.startswith("labels."):
        parts = key.split(".")
        if len(parts) != 3 or parts[2] not in LABEL_FIELDS:
            raise ExpectError(f"expect '{key}': a per-object key is labels.<object>.<field>, field one of "
                              f"{sorted(LABEL_FIELDS)}")
        if objects is not None and parts[1] not in objects:
            raise ExpectError(f"expect '{key}': no object {parts[1]!r} in the scenario (objects: {', '.join(objects)})")
        return
    if key not in known_paths(job):
        raise ExpectError(f"expect '{key}': not a number in the {'navigate.json' if job == 'navigate' else 'report.json'}"
                          f" of this job; known: {', '.join(sorted(known_paths(job)))}"
                          + (", labels.<object>.<field>" if job == "run" else ""))


def parse_expectations(table: dict, job: str = "run", objects: list[str] | None = None) -> tuple[list[Expectation], float]:
    """An ``[expect]`` table -> (expectations, min_pass_rate). Raises :class:`ExpectError`."""
    if not isinstance(table, dict):
        raise ExpectError(f"expect: expected a table of \"path\" = \"OP NUMBER\", got {table!r}")
    out, rate = [], 1.0
    for key, value in table.items():
        if key == PASS_RATE_KEY:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise ExpectError(f"expect '{PASS_RATE_KEY}': expected a number from 0 to 1, got {value!r}")
            rate = float(value)
            continue
        check_path(key, job, objects)
        op, bound = parse_comparison(key, value)
        out.append(Expectation(key, op, bound))
    return out, rate


def lookup(report: dict, path: str):
    """The value at ``path``; ``labels.<object>.<field>`` finds the object's row. KeyError if absent."""
    parts = path.split(".")
    if parts[0] == "labels" and len(parts) == 3 and isinstance(report.get("labels"), list):
        for row in report["labels"]:
            if row.get("object") == parts[1]:
                return row[parts[2]]
        raise KeyError(path)
    node = report
    for p in parts:
        if not isinstance(node, dict) or p not in node:
            raise KeyError(path)
        node = node[p]
    return node


def evaluate(exp: Expectation, report: dict) -> Outcome:
    try:
        value = lookup(report, exp.path)
    except KeyError:
        note = "needs --loop-closure" if exp.path.split(".")[-1] in LOOP_CLOSURE_KEYS else "not in the report"
        return Outcome(exp.path, exp.op, exp.bound, None, False, None, note)
    if value is None or isinstance(value, (dict, list, str)):
        return Outcome(exp.path, exp.op, exp.bound, None, False, None, f"the report holds {value!r}")
    measured = float(value)
    if not math.isfinite(measured):
        return Outcome(exp.path, exp.op, exp.bound, None, False, None, f"the report holds {value}")
    ok = bool(OPS[exp.op](measured, exp.bound))
    if exp.op in (">=", ">"):
        margin = measured - exp.bound
    elif exp.op in ("<=", "<"):
        margin = exp.bound - measured
    elif exp.op == "==":
        margin = -abs(measured - exp.bound) or 0.0
    else:
        margin = abs(measured - exp.bound)
    return Outcome(exp.path, exp.op, exp.bound, measured, ok, margin)


def evaluate_all(expectations: list[Expectation], report: dict) -> list[Outcome]:
    return [evaluate(e, report) for e in expectations]
