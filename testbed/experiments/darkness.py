"""The darkness sweep: the default scenario at light levels from 1 down to 0, with RGB input and
with depth input; labelled objects, false labels and mean error against light level (JSON + PNG)."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from testbed.experiments import EPISODE_APPLIES
from testbed.io import write_json

log = logging.getLogger(__name__)
LEVELS = (1.0, 0.5, 0.25, 0.1, 0.0)
APPLIES = EPISODE_APPLIES  # the config it honours (input and stages are swept)


def run(out_dir, scenario=None, seed=None, levels=LEVELS, inputs=("rgb", "depth"), stages=6, duration=None,
        policy="robust-mean", input_mode: str | None = None, jobs: int = 1, config=None, weights=None) -> dict:
    """``input_mode`` (the CLI's ``--input``): sweep that input only. The episodes run through the
    matrix runner (``jobs`` at once, each in ``OUT/cells/<key>/``; a rerun skips finished ones).
    ``config``: a ``testbed.settings.RunConfig``; its settings changed from the defaults go into every
    cell (input, stages and weights aside, which are this sweep's own)."""
    from stack.config import changed_keys
    from sim.scenario import DEFAULT_SCENARIO, load_scenario
    from testbed.matrix import Cell, run_cells

    if input_mode is not None:
        inputs = (input_mode,)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc = load_scenario(scenario)
    seed = sc.seed if seed is None else seed
    own = {"detector.input", "detector.stages", "detector.weights"}
    opts = {**({k: v for k, v in changed_keys(config).items() if k not in own} if config is not None else {}),
            "stages": stages, "policy": policy, **({"duration": duration} if duration is not None else {}),
            **({"weights": weights} if weights is not None else {})}
    cells = [Cell(scenario or DEFAULT_SCENARIO, seed, {**opts, "input": m, "light": light}) for m in inputs for light in levels]
    rows = []
    for cell, res in zip(cells, run_cells(cells, out, jobs=jobs)):
        if res["status"] != "ok":
            raise RuntimeError(f"darkness sweep: {cell.label()}: {res['error']}")
        rep = res["report"]
        s = rep["labels_summary"]
        rows.append({"input": cell.options["input"], "light": cell.options["light"], "labelled": s["labelled"],
                     "objects": s["objects"], "labels_in_map": s["labels_in_map"], "false_labels": s["false_labels"],
                     "map_precision": s["map_precision"], "mean_error_m": s["mean_error_m"],
                     "precision": rep["detection"]["precision"], "recall": rep["detection"]["recall"],
                     "run": str(Path(res["out_dir"]).relative_to(out))})
    result = {"scenario": rep["scenario"], "seed": rep["seed"], "stages": stages, "policy": policy, "rows": rows}
    write_json(out / "darkness.json", result)
    plot(result, out / "darkness.png")
    return result


def plot(result, path) -> None:
    from testbed.plots import plt, save

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    for input_mode, style in (("rgb", "o-"), ("depth", "s--")):
        rs = [r for r in result["rows"] if r["input"] == input_mode]
        if not rs:
            continue
        x = [r["light"] for r in rs]
        axes[0].plot(x, [r["labelled"] for r in rs], style, label=input_mode)
        axes[1].plot(x, [r["false_labels"] for r in rs], style, label=input_mode)
        axes[2].plot(x, [np.nan if r["mean_error_m"] is None else 100 * r["mean_error_m"] for r in rs], style,
                     label=input_mode)
    for ax, title in zip(axes, ("objects labelled", "false labels", "mean label error (cm)")):
        ax.set_xlabel("light level (1 = lit, 0 = dark)")
        ax.set_title(title)
        ax.invert_xaxis()
        ax.legend()
    save(fig, path)


def table(result) -> str:
    lines = [f"{'input':<6} {'light':>5} {'labelled':>9} {'labels':>7} {'false':>6} {'precision':>10} {'mean err cm':>12}"]
    for r in result["rows"]:
        err = "-" if r["mean_error_m"] is None else f"{100 * r['mean_error_m']:.1f}"
        prec = "-" if r["map_precision"] is None else f"{100 * r['map_precision']:.0f} %"
        lines.append(f"{r['input']:<6} {r['light']:>5.2f} {r['labelled']:>5}/{r['objects']} {r['labels_in_map']:>7} "
                     f"{r['false_labels']:>6} {prec:>10} {err:>12}")
    return "\n".join(lines)
