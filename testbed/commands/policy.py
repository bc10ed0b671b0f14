"""``dopeslam evaluate-policy NAME [--scenario S ...] --episodes N --out DIR``: labelling policies on
the same cached episodes, scored against ground truth, in the structure of the paper's Table 2.

NAME is a baseline (``last``, ``last-fpr``, ``best-score``, ``robust-mean``, ``evidence``,
``oracle-best``, ``oracle-worst``) or ``all``. Each scenario (default: every bundled one) runs seeds
``--first-seed`` .. ``--first-seed + N - 1``; the first run of an episode computes and caches its
perception (simulation, KISS-ICP, DOPE: minutes), later runs replay it.

Every published label is scored as ``testbed.scoring.score_map`` does (one-to-one with the true
objects of its class: correct within 0.25 m, else misplaced, or a phantom when matched to nothing);
the table gives per policy the mean label error of the matched labels, the labels in the map, the
false labels among them (misplaced + phantom), the objects without a correct label, and the map's
precision (correct / labels in the map) and recall (correct / objects).

Writes ``DIR/policy_eval.json`` (per policy, scenario and seed the map score; per policy and
scenario the mean and standard deviation over seeds; whether the best non-oracle baseline beats
``last`` and ``last-fpr``) and ``DIR/policy_table.md``.
"""
from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

from stack.errors import UsageError

log = logging.getLogger(__name__)

PAPER_ROWS = {"last": "original", "last-fpr": "fpr", "oracle-best": "best", "oracle-worst": "worst"}


# testbed.envs.policies.BASELINES' names, here so that building the parser imports no env (a test keeps them equal)
BASELINE_NAMES = ("last", "last-fpr", "best-score", "robust-mean", "evidence", "oracle-best", "oracle-worst")


def register(sub) -> None:
    p = sub.add_parser("evaluate-policy", help="labelling policies on cached episodes, scored like the paper's Table 2")
    p.add_argument("name", help=f"baseline: {', '.join(BASELINE_NAMES)}, or all")
    p.add_argument("--scenario", action="append", default=None,
                   help="bundled name or TOML path (repeatable; default: every bundled scenario)")
    p.add_argument("--episodes", type=int, default=10, help="seeds per scenario")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--out", default="out/policy")
    p.add_argument("--duration", type=float, default=None, help="override the scenarios' duration (s)")
    p.add_argument("--input", dest="input_mode", choices=["auto", "rgb", "depth"], default="auto",
                   help="DOPE input (auto: depth in complete darkness, else rgb)")
    p.add_argument("--stages", type=int, choices=range(1, 7), default=6, metavar="1-6")
    p.add_argument("--weights", default=None, help="DOPE weights file (default: the shipped ones)")
    p.add_argument("--cache", default=None, help="perception cache folder (default: $DOPESLAM_CACHE or "
                                                   "~/.cache/dopeslam/perception)")
    p.add_argument("--max-objects", type=int, default=16, help="object slots (candidate objects) per episode")
    p.add_argument("--jobs", type=int, default=1, help="build missing episode caches in this many processes")
    p.add_argument("--ray", action="store_true", help="build missing episode caches as tasks on a local Ray runtime")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="build them on an existing Ray cluster (its nodes share this machine's cache folder)")
    p.set_defaults(func=run)


def run(args) -> int:
    from sim.scenario import bundled_scenarios
    from testbed.envs.policies import BASELINES

    names = list(BASELINES) if args.name == "all" else [args.name]
    unknown = [n for n in names if n not in BASELINES]
    if unknown:
        raise UsageError(f"unknown policy {unknown[0]!r}; expected one of {sorted(BASELINES)} or all")
    if args.episodes < 1:
        raise UsageError(f"--episodes: expected at least 1, got {args.episodes}")
    scenarios = args.scenario or bundled_scenarios()
    env_kwargs = {"duration": args.duration, "input_mode": args.input_mode, "stages": args.stages,
                  "weights": args.weights, "cache_dir": args.cache, "max_objects": args.max_objects}
    seeds = range(args.first_seed, args.first_seed + args.episodes)
    if args.jobs > 1 or args.ray or args.ray_address:
        prebuild(scenarios, seeds, env_kwargs, args.jobs, ray=args.ray, ray_address=args.ray_address)
    result = evaluate(names, scenarios, seeds, env_kwargs)
    paths = write_outputs(result, args.out)
    print(table_markdown(result))
    print(f"wrote {paths[0]} and {paths[1]}")
    return 0


def prebuild(scenarios, seeds, env_kwargs: dict, jobs: int, ray: bool = False,
             ray_address: str | None = None) -> list[str]:
    """Build the perception caches of every (scenario, seed) through the matrix runner
    (:func:`testbed.matrix.run_cells`: ``jobs`` local processes, or Ray tasks), each running its own
    simulation, odometry and DOPE; episodes already cached are only read. The caches' file stems, in order.
    Each cell's small report lands under ``$DOPESLAM_CACHE/perception-cells/`` (resumed like any sweep)."""
    from testbed.matrix import Cell, run_cells
    from testbed.settings import cache_dir

    opts = {"job": "perception-cache", **{k: (str(v) if isinstance(v, os.PathLike) else v)
                                          for k, v in env_kwargs.items() if v is not None}}
    cells = [Cell(str(sc), int(s), opts) for sc in scenarios for s in seeds]
    log.info("building %d episode caches with %d workers", len(cells), jobs)
    results = run_cells(cells, cache_dir("perception-cells"), jobs=jobs, ray=ray, ray_address=ray_address)
    failed = [r for r in results if r["status"] != "ok"]
    if failed:
        log.warning("%d episode caches failed to build (they are built again, in this process): %s",
                    len(failed), "; ".join(f"{r['cell'].label()}: {r['error']}" for r in failed[:3]))
    return [r["report"]["cache_stem"] for r in results if r["status"] == "ok"]


def evaluate(names: list[str], scenarios: list[str], seeds, env_kwargs: dict) -> dict:
    """Run each policy on each (scenario, seed); ``env_kwargs`` go to ``DopeSlamLabellingEnv``."""
    from testbed.envs.labelling import DopeSlamLabellingEnv
    from testbed.envs.policies import make_policy, run_episode

    seeds = [int(s) for s in seeds]
    runs = []
    for sc in scenarios:
        env = DopeSlamLabellingEnv(scenario=sc, seeds=seeds, **env_kwargs)
        for i, seed in enumerate(seeds):
            log.info("%s seed %d: %s", sc, seed, ", ".join(names))
            for name in names:
                r = run_episode(env, make_policy(name, env), options={"episode": i})
                runs.append({"policy": name, "scenario": str(sc), "seed": seed, "input": r["episode"]["input"],
                             "frames": r["steps"], "return": r["return"], **r["summary"], "labels": r["labels"]})
        env.close()
    slots = env_kwargs.get("max_objects") or 16
    for sc in scenarios:
        dropped = max_dropped(runs, str(sc))
        if dropped:
            log.warning("%s: up to %d detections per episode found no free object slot (--max-objects %d): "
                        "the policies are scored on a truncated map; raise --max-objects", sc, dropped, slots)
    return summarise(names, [str(s) for s in scenarios], seeds, runs)


def max_dropped(runs: list[dict], scenario: str) -> int:
    """The most detections one episode of ``scenario`` dropped for want of a free object slot."""
    return max((r.get("dropped_detections") or 0 for r in runs if r["scenario"] == scenario), default=0)


def _stats(values: list) -> dict:
    import numpy as np

    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return {"mean": float(np.mean(v)) if v else None, "std": float(np.std(v)) if v else None, "n": len(v)}


def summarise(names: list[str], scenarios: list[str], seeds: list[int], runs: list[dict]) -> dict:
    groups = {}
    for name in names:
        per_sc = {}
        for sc in scenarios + ["all"]:
            rs = [r for r in runs if r["policy"] == name and (sc == "all" or r["scenario"] == sc)]
            if not rs:
                continue
            per_sc[sc] = {
                "episodes": len(rs),
                "objects": int(rs[0]["objects"]) if sc != "all" else None,
                "mean_error_cm": _stats([None if r["mean_error_m"] is None else 100 * r["mean_error_m"] for r in rs]),
                "labels_in_map": _stats([r["labels_in_map"] for r in rs]),
                "false_labels": _stats([r["false_labels"] for r in rs]),
                "misplaced": _stats([r["misplaced"] for r in rs]),
                "phantom": _stats([r["phantom"] for r in rs]),
                "missing": _stats([r["missing"] for r in rs]),
                "map_precision": _stats([r["map_precision"] for r in rs]),
                "map_recall": _stats([r["map_recall"] for r in rs]),
                "candidates": _stats([r.get("candidates") for r in rs]),
                "return": _stats([r["return"] for r in rs]),
            }
        groups[name] = per_sc
    return {"policies": names, "scenarios": scenarios, "seeds": seeds, "by_policy": groups,
            "targets": targets(groups, scenarios), "paper_table2": paper_reference(),
            "runs": [{k: v for k, v in r.items() if k != "labels"} for r in runs]}


def targets(groups: dict, scenarios: list[str]) -> dict:
    """Per scenario: does the best non-oracle baseline beat ``last`` and ``last-fpr`` on mean label
    error with no more false labels (means over seeds)?"""
    out = {}
    for sc in scenarios:
        def get(name, key):
            return groups.get(name, {}).get(sc, {}).get(key, {}).get("mean")
        cands = [n for n in groups if not n.startswith("oracle") and get(n, "mean_error_cm") is not None]
        refs = [n for n in ("last", "last-fpr") if n in groups]
        if not cands or not refs:
            continue
        best = min(cands, key=lambda n: get(n, "mean_error_cm"))
        ok = all(get(r, "mean_error_cm") is None or
                 (get(best, "mean_error_cm") < get(r, "mean_error_cm") and get(best, "false_labels") <= get(r, "false_labels"))
                 for r in refs if r != best)
        out[sc] = {"best_non_oracle": best, "beats_last_and_last_fpr": bool(ok and best not in refs)}
    return out


def paper_reference() -> dict | None:
    """The paper's Table 2 figures (``testbed/experiments/paper_results.json``, shipped with the package)."""
    p = Path(__file__).resolve().parents[1] / "experiments" / "paper_results.json"
    if p.exists():
        return json.loads(p.read_text()).get("experiment_3_localization")
    return None


def _fmt(s: dict | None, digits: int = 1) -> str:
    if not s or s.get("mean") is None:
        return "-"
    return f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"


def _mean(s: dict | None, digits: int = 1) -> str:
    return "-" if not s or s.get("mean") is None else f"{s['mean']:.{digits}f}"


def table_markdown(result: dict) -> str:
    paper = result.get("paper_table2") or {}
    lines = []
    for sc in result["scenarios"] + (["all"] if len(result["scenarios"]) > 1 else []):
        lines.append(f"\n### {sc} ({len(result['seeds'])} seeds)\n")
        lines.append("| policy | paper row | mean label error (cm) | labels in map | false labels (misplaced + phantom) "
                     "| missing | map precision | map recall | paper error (cm) | paper false labels |")
        lines.append("|---|---|---|---|---|---|---|---|---|---|")
        for name in result["policies"]:
            g = result["by_policy"][name].get(sc)
            if g is None:
                continue
            row = PAPER_ROWS.get(name, "")
            pe = paper.get("mean_distance_cm", {}).get(row, "") if row else ""
            pf = paper.get("false_labels_of_6", {}).get(row, "") if row else ""
            lines.append(f"| {name} | {row or '-'} | {_fmt(g['mean_error_cm'])} | {_fmt(g['labels_in_map'], 1)} | "
                         f"{_fmt(g['false_labels'], 2)} ({_mean(g['misplaced'])} + {_mean(g['phantom'])}) | "
                         f"{_fmt(g['missing'], 2)} | {_fmt(g['map_precision'], 2)} | {_fmt(g['map_recall'], 2)} | "
                         f"{pe if pe != '' else '-'} | {pf if pf != '' else '-'} |")
        dropped = max_dropped(result.get("runs", []), sc) if sc != "all" else 0
        if dropped:
            lines.append(f"\nwarning: up to {dropped} detections per episode found no free object slot; "
                         "raise --max-objects")
        t = result["targets"].get(sc)
        if t:
            lines.append(f"\nbest non-oracle baseline: {t['best_non_oracle']}; beats last and last-fpr with no more "
                         f"false labels: {'yes' if t['beats_last_and_last_fpr'] else 'no'}")
    return "\n".join(lines).lstrip()


def write_outputs(result: dict, out_dir) -> tuple[Path, Path]:
    from testbed.io import write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    j, t = out / "policy_eval.json", out / "policy_table.md"
    write_json(j, result)
    tmp = t.with_suffix(".md.tmp")
    tmp.write_text("# Labelling policies (mean ± standard deviation over seeds)\n\n" + table_markdown(result) + "\n")
    tmp.replace(t)
    return j, t
