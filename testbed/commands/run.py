"""``dopeslam run [SCENARIO] --out DIR --seed N [--light L] [--input rgb|depth] [--stages 1-6] [--fpr/--no-fpr]
[--policy NAME|MODULE:FUNCTION] [--detector MODULE:CLASS]``."""
from __future__ import annotations

import argparse


def add_dope_options(p: argparse.ArgumentParser, defaults: bool = True) -> None:
    """The options of every command that runs DOPE. ``defaults=False``: unset options are None, so the
    command (e.g. an experiment with the paper's own input) keeps its default."""
    p.add_argument("--input", dest="input_mode", choices=["rgb", "depth"], default="rgb" if defaults else None,
                   help="DOPE input image" + ("" if defaults else " (default: the experiment's own)"))
    p.add_argument("--stages", type=int, choices=range(1, 7), default=6 if defaults else None, metavar="1-6",
                   help="DOPE stages to run")
    p.add_argument("--fpr", action=argparse.BooleanOptionalAction, default=True, help="false-positive reduction")
    p.add_argument("--weights", default=None, help="weights file (default: the shipped ones for --input)")


def register(sub) -> None:
    p = sub.add_parser("run", help="the main job: a scored drive-through episode (report, labels.xlsx, map.png)")
    p.add_argument("scenario", nargs="?", default=None, help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--out", default="out/run")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--light", type=float, default=None, help="override the scenario's light level (0-1)")
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--policy", default="robust-mean",
                   help="labelling policy: last, last-fpr, best-score, robust-mean, ..., or MODULE:FUNCTION "
                        "(observations -> stack.object_store.Label or None)")
    p.add_argument("--detector", default=None, metavar="MODULE:CLASS",
                   help="your detector instead of DOPE: a class constructed with no arguments, with "
                        "detect(frame) -> list[Detection] (stack.interfaces.Detector); --input, --stages, "
                        "--fpr and --weights then do not apply. Ground truth: "
                        "testbed.oracle_detector:OracleDetector")
    p.add_argument("--loop-closure", action="store_true",
                   help="close loops (vocabulary tree + LiDAR verification + pose graph); labels move with them")
    add_dope_options(p)
    p.set_defaults(func=run)

    p = sub.add_parser("score", help="publish saved runs' maps again (evidence settings) and score the whole map")
    p.add_argument("runs", nargs="+", help="folders written by `dopeslam run`")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="FIELD=VALUE",
                   help="an evidence setting (stack.evidence.EvidenceConfig), e.g. min_observations=3")
    p.add_argument("--out", default=None, help="write the scores as JSON here")
    p.set_defaults(func=score)


def run(args) -> int:
    import sys

    from stack.interfaces import ImportPathError, load_detector, resolve_policy
    from testbed.run import print_summary, run_episode

    try:
        policy = resolve_policy(args.policy)
        detector = load_detector(args.detector) if args.detector else None
    except ImportPathError as e:
        print(f"dopeslam run: --{e}", file=sys.stderr)  # "--detector 'x:Y': what is wrong"
        return 2
    report = run_episode(args.scenario, args.out, args.seed, args.light, args.input_mode, args.stages, args.fpr,
                         policy, args.duration, args.weights, detector=detector, loop_closure=args.loop_closure)
    print_summary(report)
    print(f"wrote {args.out}/report.json, labels.xlsx, map.png, estimate_tum.txt, groundtruth_tum.txt")
    return 0


def score(args) -> int:
    import json
    import sys

    import numpy as np
    from pydantic import ValidationError

    from stack.evidence import EvidenceConfig
    from testbed.scoring import RunDirError, rescore_run

    try:
        fields = dict(s.split("=", 1) for s in args.settings)
        evidence = EvidenceConfig(**fields)
    except ValueError as e:
        first = e.errors()[0] if isinstance(e, ValidationError) else None
        where = f"field '{first['loc'][0]}': {first['msg']}" if first else "expected FIELD=VALUE"
        print(f"dopeslam score: --set {where}; fields: {sorted(EvidenceConfig.model_fields)}", file=sys.stderr)
        return 2
    rows = []
    for run_dir in args.runs:
        try:
            s = rescore_run(run_dir, evidence)
        except RunDirError as e:
            print(f"dopeslam score: {e}", file=sys.stderr)
            return 2
        rows.append(s)
        prec = "-" if s["map_precision"] is None else f"{100 * s['map_precision']:.0f} %"
        err = "-" if s["mean_error_m"] is None else f"{100 * s['mean_error_m']:.1f} cm"
        print(f"{run_dir}: {s['labels_in_map']} labels, {s['correct_labels']} correct, {s['misplaced']} misplaced, "
              f"{s['phantom']} phantom; precision {prec}, {s['correct_labels']}/{s['objects']} labelled, "
              f"mean error {err}, {s['candidates']} candidates")
    n_map, n_ok = sum(s["labels_in_map"] for s in rows), sum(s["correct_labels"] for s in rows)
    n_obj = sum(s["objects"] for s in rows)
    errs = [s["mean_error_m"] for s in rows if s["mean_error_m"] is not None]
    print(f"{len(rows)} runs: {n_map} labels, {n_ok} correct, {n_map - n_ok} false; precision "
          f"{'-' if not n_map else f'{100 * n_ok / n_map:.1f} %'}, recall {100 * n_ok / max(1, n_obj):.1f} %, "
          f"mean error {'-' if not errs else f'{100 * float(np.mean(errs)):.1f} cm'} (mean of the runs' means); "
          f"{sum(1 for s in rows if s['false_labels'] == 0)}/{len(rows)} maps without a false label")
    if args.out:
        from testbed.simulate import write_json

        write_json(args.out, {"evidence": evidence.model_dump(), "runs": rows})
    return 0
