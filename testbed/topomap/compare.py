"""``dopeslam compare [SCENARIO] --out DIR``: DOPESLAM and the monocular semantic
topological map on the same episodes (scenario, seed, light), lit and dark, side by side.

Per episode and stack:

* objects found: DOPESLAM - objects with a label within 25 cm of the truth (``testbed.run``);
  seed 2 - objects whose class is attributed to a node whose image shows them (>= 30 % visible);
* false attributions: DOPESLAM - every false label in the map (``testbed.scoring``: misplaced, more
  than 25 cm off, or phantom, matched to no object); candidates it did not publish are not labels;
  seed 2 - attributes on nodes whose image shows no object of that class;
* localisation error: DOPESLAM - LiDAR odometry ATE RMSE (map -> world with the known start);
  seed 2 - RMSE of the nodes' camera positions (map -> world with the first node's true pose);
* compute per camera frame: DOPESLAM - odometry + DOPE + fusion seconds over the camera frames;
  seed 2 - features + pose + place description + detector seconds over the camera frames.

Lit runs use the scenario's light; dark runs light 0. DOPESLAM runs its RGB network when lit and
its depth network in the dark (the paper's darkness mode); the monocular system has only RGB.
Writes ``DIR/compare.json`` and ``DIR/compare.md`` (the table).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

from stack.topomap.topological_map import score_map
from testbed.topomap.navigate import build_map, load_detector, load_tree, node_truth
from testbed.topomap.stream import camera_stream
from testbed.io import write_json

log = logging.getLogger(__name__)
VISIBLE = 0.3


def visible_sets(topo, stream) -> dict[int, set]:
    out = {}
    for n in topo.nodes:
        out[n.id] = {o.name for k, o in enumerate(stream.objects) if stream.object_in_view(n.frame, k, VISIBLE)}
    return out


def run_topomap(scenario, seed: int, light: float, duration=None, tree=None, detector=None) -> dict:
    t0 = time.perf_counter()
    stream = camera_stream(scenario, seed=seed, light=light, duration=duration)
    topo = build_map(stream, tree, detector)
    secs = topo.meta.get("seconds", {})
    truth = node_truth(topo, stream)
    T_world_map = truth[0] if topo.nodes else None
    score = score_map(topo, stream.objects, truth, visible_sets(topo, stream), T_world_map)
    s = score["summary"]
    return {"stack": "topological-map", "scenario": stream.scenario, "seed": stream.seed, "light": stream.light,
            "objects": len(stream.objects), "found": s["found"], "false_attributions": s["false_attributions"],
            "localisation_error_m": s["node_position_rmse_m"], "nodes": s["nodes"],
            "segments": len(topo.meta.get("segments", [])),
            "compute_per_frame_s": float(sum(secs.values())) / max(1, len(stream)),
            "compute_split_s": secs, "wall_seconds": time.perf_counter() - t0, "per_object": score["objects"]}


def run_dopeslam(scenario, seed: int, light: float, out_dir: Path, duration=None) -> dict:
    from testbed.run import run_episode

    mode = "rgb" if light > 0 else "depth"
    rep = run_episode(scenario, out_dir, seed=seed, light=light, input_mode=mode, duration=duration)
    s = rep["labels_summary"]
    ts = rep["time_split_s"]
    frames = max(1, rep["detection"]["frames"])
    return {"stack": f"dopeslam-{mode}", "scenario": rep["scenario"], "seed": rep["seed"], "light": rep["light"],
            "objects": s["objects"], "found": s["correct_labels"],
            "false_attributions": int(s["false_labels"]),  # every false label in the map, phantoms included
            "map_precision": s["map_precision"],
            "localisation_error_m": rep["odometry"]["ate_rmse_m"],
            "compute_per_frame_s": (ts["odometry"] + ts["dope"] + ts["fusion"]) / frames,
            "compute_split_s": ts, "wall_seconds": rep["wall_seconds"],
            "mean_label_error_m": s["mean_error_m"]}


def compare(scenario=None, out_dir="out/compare", seeds: list[int] | None = None, duration=None) -> dict:
    from sim.scenario import load_scenario

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc = load_scenario(scenario)
    seeds = seeds or [sc.seed]
    lights = {"lit": sc.light if sc.light > 0 else 1.0, "dark": 0.0}
    tree, detector = load_tree(), load_detector()
    rows = []
    for cond, light in lights.items():
        for seed in seeds:
            log.info("%s, %s, seed %d: DOPESLAM", sc.name, cond, seed)
            try:
                a = run_dopeslam(scenario, seed, light, out / f"dopeslam_{cond}_s{seed}", duration)
            except (ImportError, FileNotFoundError, ValueError) as exc:  # a stack that cannot run is reported, not hidden
                a = {"stack": "dopeslam", "seed": seed, "light": light, "error": str(exc)}
            log.info("%s, %s, seed %d: monocular topological map", sc.name, cond, seed)
            b = run_topomap(scenario, seed, light, duration, tree, detector)
            for r in (a, b):
                r["condition"] = cond
                rows.append(r)
            write_json(out / "compare.json", {"scenario": sc.name, "rows": rows})
    report = {"scenario": sc.name, "seeds": seeds, "lights": lights, "rows": rows}
    write_json(out / "compare.json", report)
    (out / "compare.md").write_text(table(report))
    return report


def table(report: dict) -> str:
    lines = [f"Scenario `{report['scenario']}`, seeds {report['seeds']}", "",
             "| condition | stack | objects found | false attributions | precision | localisation error (m) | "
             "compute per frame (ms) |",
             "|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        if "error" in r:
            lines.append(f"| {r['condition']} | {r['stack']} | failed to run: {r['error']} | | | | |")
            continue
        le = "-" if r["localisation_error_m"] is None else f"{r['localisation_error_m']:.3f}"
        n = r["found"] + r["false_attributions"]
        prec = f"{100 * r['found'] / n:.0f} %" if n else "-"  # the monocular map: found / (found + false)
        lines.append(f"| {r['condition']} (light {r['light']:.1f}, seed {r['seed']}) | {r['stack']} | "
                     f"{r['found']}/{r['objects']} | {r['false_attributions']} | {prec} | {le} | "
                     f"{1000 * r['compute_per_frame_s']:.0f} |")
    return "\n".join(lines) + "\n"


def main_args(args) -> int:
    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else None
    report = compare(args.scenario, args.out, seeds, args.duration)
    print(table(report))
    print(f"wrote {args.out}/compare.json and compare.md")
    return 0
