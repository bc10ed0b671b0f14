"""``dopeslam sweep``: scenarios (or suites) x seeds x ``--grid`` values of any config key, run by the
matrix runner (:mod:`testbed.matrix`), one row per cell.

Outputs in ``OUT/``:

- ``results.csv``: one row per cell in a stable order (scenario, then grid point, then seed): the
  cell's scenario, seed, grid values, key and status (``ok``/``error`` with its message), then every
  scalar of its ``report.json`` flattened to dotted column names. Timing and provenance columns
  (``testbed.matrix.VOLATILE``) are listed in ``sweep.json``; every other column is the same whatever
  the backend or the number of workers;
- ``rows.jsonl``: the same rows, appended as each cell ends (a Ctrl-C or a killed driver keeps them);
- ``sweep.json``: what was asked, the columns, the volatile columns, counts and wall time;
- ``<metric>_vs_<grid key>.png``: each headline metric against each grid key, mean and spread over the
  seeds, a line per scenario (without a grid: against the scenario);
- ``cells/<key>/``: each cell's output folder, as ``dopeslam run`` writes it.
"""
from __future__ import annotations

import csv
import io
import itertools
import json
import logging
import time
from pathlib import Path

from testbed.matrix import VOLATILE, Cell, MatrixError, parse_seeds, run_cells

log = logging.getLogger(__name__)

ID_COLUMNS = ["scenario", "seed", "key", "status", "error"]
HEADLINES = ["labels_summary.correct_labels", "labels_summary.false_labels", "labels_summary.map_precision",
             "labels_summary.mean_error_m", "odometry.ate_rmse_m"]


def flatten(report: dict | None, prefix: str = "") -> dict:
    """Every scalar of a report as ``{"a.b.c": value}`` (lists are left out: they are per-object rows)."""
    out = {}
    for k, v in (report or {}).items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, name + "."))
        elif v is None or isinstance(v, (bool, int, float, str)):
            out[name] = v
    return out


def expand(targets: list[str], seeds: str | None, grid: list[str], sets: list[str]) -> tuple[list[Cell], list[str]]:
    """The cells of a sweep, in order, and the grid's keys. A target is a scenario (bundled name or
    TOML path) or a suite (``testbed/suites/*.toml`` by name, or a suite file): a suite gives its cases'
    scenarios, options and seeds; ``seeds`` replaces them. ``sets``: ``key=value`` on every cell."""
    from stack.config import ConfigError, parse_assignment, parse_grid
    from testbed.testing.suite import SuiteError, load_plan

    try:
        plan = load_plan(targets)
    except SuiteError as e:
        raise MatrixError(str(e)) from None
    override = parse_seeds(seeds) if seeds is not None else None
    try:
        grid_items = [parse_grid(g) for g in grid]
        fixed = dict(parse_assignment(s, "--set") for s in sets)
    except ConfigError as e:
        raise MatrixError(str(e)) from None
    keys = [k for k, _ in grid_items]
    if len(set(keys)) != len(keys):
        raise MatrixError(f"--grid: a key is given twice: {keys}")
    cells = []
    for case in plan.cases:
        if case.options.get("job", "run") != "run":
            raise MatrixError(f"{case.source or case.scenario}: case {case.id!r} is a {case.options['job']} job; "
                              f"a sweep runs the run job")
        for point in itertools.product(*(vals for _, vals in grid_items)):
            options = {**{k: v for k, v in case.options.items() if k != "job"}, **fixed, **dict(zip(keys, point))}
            for s in override if override is not None else case.seeds:
                cells.append(Cell(case.scenario, s, options))
    return cells, keys


def row_of(result: dict, grid_keys: list[str]) -> dict:
    cell = result["cell"]
    row = {"scenario": str(cell.scenario), "seed": cell.seed, "key": result["key"], "status": result["status"],
           "error": result["error"] or ""}
    for k in grid_keys:
        row[f"grid.{k}"] = cell.options.get(k)
    row.update(flatten(result["report"]))
    return row


def _columns(rows: list[dict], grid_keys: list[str]) -> list[str]:
    first = ID_COLUMNS + [f"grid.{k}" for k in grid_keys]
    rest = sorted({c for r in rows for c in r} - set(first))
    return first + rest


def write_csv(path: Path, rows: list[dict], columns: list[str]) -> None:
    from testbed.io import write_text

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: ("" if r.get(c) is None else r.get(c)) for c in columns})
    write_text(path, buf.getvalue())


def stable_columns(columns: list[str]) -> list[str]:
    """The columns that must not change with the backend or the worker count."""
    return [c for c in columns if not VOLATILE.match(c)]


def sweep(targets: list[str], out: str | Path, seeds: str | None = None, grid: list[str] | None = None,
          sets: list[str] | None = None, jobs: int = 1, ray: bool = False, ray_address: str | None = None,
          collect_files: bool = False, progress: bool = True, plots: bool = True) -> dict:
    """Run a sweep into ``out``; returns the summary written to ``sweep.json``."""
    from testbed.io import write_json

    out = Path(out)
    cells, grid_keys = expand(targets, seeds, grid or [], sets or [])
    if not cells:
        raise MatrixError("nothing to run: no cells (check the seeds and the suite)")
    out.mkdir(parents=True, exist_ok=True)
    journal = out / "rows.jsonl"
    t0 = time.perf_counter()
    with open(journal, "a", encoding="utf-8") as j:
        def save(i: int, result: dict) -> None:
            if result.get("resumed"):
                return
            j.write(json.dumps({"i": i, **row_of(result, grid_keys)}, allow_nan=False, default=str) + "\n")
            j.flush()

        results = run_cells(cells, out, jobs=jobs, ray=ray, ray_address=ray_address, progress=progress,
                            collect_files=collect_files, on_result=save)
    wall = time.perf_counter() - t0
    rows = [row_of(r, grid_keys) for r in results]
    columns = _columns(rows, grid_keys)
    write_csv(out / "results.csv", rows, columns)
    pngs = plot_sweep(rows, grid_keys, out) if plots else []
    summary = {"targets": targets, "seeds": seeds, "grid": grid or [], "set": sets or [], "cells": len(rows),
               "ok": sum(r["status"] == "ok" for r in rows), "errors": sum(r["status"] != "ok" for r in rows),
               "resumed": sum(bool(r.get("resumed")) for r in results),
               "backend": "ray" if (ray or ray_address) else f"processes x{jobs}", "wall_seconds": wall,
               "columns": columns, "volatile_columns": [c for c in columns if VOLATILE.match(c)],
               "plots": [p.name for p in pngs]}
    write_json(out / "sweep.json", summary)
    return summary


def _num(v):
    return v if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def plot_sweep(rows: list[dict], grid_keys: list[str], out: Path) -> list[Path]:
    """One PNG per headline metric and grid key (or per metric against the scenario without a grid)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from testbed.io import atomic_path

    written = []
    axes_keys = [f"grid.{k}" for k in grid_keys] or ["scenario"]
    for metric in HEADLINES:
        if not any(_num(r.get(metric)) is not None for r in rows):
            continue
        for xkey in axes_keys:
            fig, ax = plt.subplots(figsize=(6, 3.6))
            series = sorted({r["scenario"] for r in rows}) if xkey != "scenario" else ["all"]
            xs = list(dict.fromkeys(str(r.get(xkey)) for r in rows))
            for si, s in enumerate(series):
                mean, lo, hi = [], [], []
                for x in xs:
                    vals = [_num(r.get(metric)) for r in rows if str(r.get(xkey)) == x
                            and (s == "all" or r["scenario"] == s)]
                    vals = [v for v in vals if v is not None]
                    mean.append(np.mean(vals) if vals else np.nan)
                    lo.append(np.min(vals) if vals else np.nan)
                    hi.append(np.max(vals) if vals else np.nan)
                pos = np.arange(len(xs)) + 0.08 * (si - (len(series) - 1) / 2)
                m = np.array(mean)
                ax.errorbar(pos, m, yerr=[m - np.array(lo), np.array(hi) - m], marker="o", capsize=3,
                            label=Path(s).stem if s != "all" else None)
            ax.set_xticks(np.arange(len(xs)), [Path(x).stem if xkey == "scenario" else x for x in xs],
                          rotation=20 if xkey == "scenario" else 0)
            ax.set_xlabel(xkey.removeprefix("grid."))
            ax.set_ylabel(metric)
            ax.set_title(f"{metric}: mean, min-max over seeds", fontsize=9)
            if len(series) > 1:
                ax.legend(fontsize=7)
            fig.tight_layout()
            name = f"{metric.split('.')[-1]}_vs_{xkey.removeprefix('grid.').replace('.', '_')}.png"
            with atomic_path(out / name) as tmp:
                fig.savefig(tmp, dpi=110, format="png")
            plt.close(fig)
            written.append(out / name)
    return written
