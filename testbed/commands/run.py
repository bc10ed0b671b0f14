"""``dopeslam run [SCENARIO] --out DIR --seed N [--light L] [--input rgb|depth] [--stages 1-6] [--fpr/--no-fpr]
[--policy NAME|MODULE:FUNCTION] [--detector MODULE:CLASS]``."""
from __future__ import annotations

import argparse

from testbed.commands.options import add_config_options, config_error, config_from_args


def add_dope_options(p: argparse.ArgumentParser, defaults: bool = True,
                     unset: str = " (default: the experiment's own)") -> None:
    """The options of every command that runs DOPE. ``defaults=False``: unset options are None, so the
    command (e.g. an experiment with the paper's own input, or the config's) keeps its default, and
    ``unset`` ends the help."""
    p.add_argument("--input", dest="input_mode", choices=["rgb", "depth"], default="rgb" if defaults else None,
                   help="DOPE input image" + ("" if defaults else unset))
    p.add_argument("--stages", type=int, choices=range(1, 7), default=6 if defaults else None, metavar="1-6",
                   help="DOPE stages to run" + ("" if defaults else unset))
    p.add_argument("--fpr", action=argparse.BooleanOptionalAction, default=True if defaults else None,
                   help="false-positive reduction" + ("" if defaults else unset))
    p.add_argument("--weights", default=None, help="weights file (default: the shipped ones for --input)")


CONFIG_DEFAULT = " (default: the config's, see --config and --set)"


def add_odometry_option(p: argparse.ArgumentParser) -> None:
    """``--odometry NAME|MODULE:CLASS`` on every command that runs the stack."""
    p.add_argument("--odometry", default=None, metavar="NAME|MODULE:CLASS",
                   help="the odometry: kiss-icp (default, LiDAR), wheel (wheel odometry only), an installed "
                        "package's entry point (group dopeslam.odometry), or MODULE:CLASS, a class called with "
                        "the LiDAR's mounting T_base_lidar (4x4) (stack.interfaces.Odometry)")


def add_dynamic_options(p: argparse.ArgumentParser) -> None:
    """``--fault``, ``--store`` and ``--retire`` (docs/faults.md, docs/dynamic.md)."""
    p.add_argument("--fault", dest="faults", action="append", default=[], metavar="NAME=VALUE",
                   help="a sensor fault over the scenario's [faults], e.g. lidar_drop=0.2, camera_drop=0.2, "
                        "camera_latency=0.05 (seconds), wheel_slip=0.1; every name in docs/faults.md")
    p.add_argument("--store", default=None, metavar="PATH",
                   help="an object store (labels.xlsx or labels.json) from an earlier run: start from it and "
                        "save the updated map there (rows you marked edited stay as you left them)")
    p.add_argument("--retire", action=argparse.BooleanOptionalAction, default=None,
                   help="retire labels whose place the depth images show empty (stack.retire; default: the "
                        "config's retire.enabled, on)")


def check_dynamic_options(args, command: str) -> int | None:
    """Exit status 2 with a one-line error for a bad --fault or --store, else None."""
    import sys
    from pathlib import Path

    from sim.faults import FaultError, parse_overrides

    try:
        parse_overrides(getattr(args, "faults", []) or [])
    except FaultError as e:
        print(f"dopeslam {command}: --{e}", file=sys.stderr)
        return 2
    store = getattr(args, "store", None)
    if store is not None:
        p = Path(store)
        if p.suffix.lower() not in (".xlsx", ".json"):
            print(f"dopeslam {command}: --store {store}: expected a .xlsx or .json file", file=sys.stderr)
            return 2
        if p.exists():
            from stack.object_store import ObjectStoreError, read_objects

            try:
                read_objects(p)
            except ObjectStoreError as e:
                print(f"dopeslam {command}: --store {e}", file=sys.stderr)
                return 2
    return None


def add_view_options(p: argparse.ArgumentParser) -> None:
    """``--view rerun`` and ``--view-save FILE.rrd`` (testbed/view.py, docs/live_view.md)."""
    p.add_argument("--view", choices=["rerun"], default=None,
                   help="watch the job live in the Rerun viewer: LiDAR scan and map, camera image with detections "
                        "and FPR verdicts, true and estimated path, labels with their truth (needs the view extra; "
                        "default: no live view)")
    p.add_argument("--view-save", default=None, metavar="FILE.rrd",
                   help="write the live view to a Rerun recording file (open it with `rerun FILE.rrd`; "
                        "default: none)")


def open_view(args, command: str):
    """(the view --view/--view-save asked for or None, exit status 2 when it cannot start, else None)."""
    if getattr(args, "view", None) is None and not getattr(args, "view_save", None):
        return None, None
    import sys

    from testbed.view import ViewError, make_view

    try:
        return make_view(args.view, args.view_save), None
    except ViewError as e:
        print(f"dopeslam {command}: {e}", file=sys.stderr)
        return None, 2


def check_loop_closure(enabled: bool, command: str) -> int | None:
    """Exit status 2 with a one-line error naming the pip command when loop closure lacks GTSAM."""
    if not enabled:
        return None
    import sys

    from stack.loops.closure import require_gtsam

    try:
        require_gtsam()
    except ModuleNotFoundError as e:
        print(f"dopeslam {command}: {e}", file=sys.stderr)
        return 2
    return None


def register(sub) -> None:
    p = sub.add_parser("run", help="the main job: a scored drive-through episode (report, labels.xlsx, map.png)")
    p.add_argument("scenario", nargs="?", default=None, help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--out", default="out/run")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--light", type=float, default=None, help="override the scenario's light level (0-1)")
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--profile", choices=["full", "fast"], default=None,
                   help="fast: the camera (and DOPE) at half the scenario's rate, no segmentation image, no per-image "
                        "recall; for large sweeps, what it costs in docs/speed.md (default: the config's run.profile, full)")
    p.add_argument("--lidar", choices=["points", "packets"], default=None,
                   help="packets: the Velodyne publishes VLP-32C data packets (ranges in 4 mm steps) and each sweep "
                        "is their decoding, as on a robot that records /velodyne_packets (default: the scenario's "
                        "[sensors] lidar_packets)")
    p.add_argument("--policy", default=None,
                   help="labelling policy: last, last-fpr, best-score, robust-mean (default), ..., or MODULE:FUNCTION "
                        "(observations -> stack.object_store.Label or None)")
    p.add_argument("--detector", default=None, metavar="MODULE:CLASS",
                   help="your detector instead of DOPE: a class constructed with no arguments, with "
                        "detect(frame) -> list[Detection] (stack.interfaces.Detector); --input, --stages, "
                        "--fpr and --weights then do not apply. Ground truth: "
                        "testbed.oracle_detector:OracleDetector")
    p.add_argument("--loop-closure", action="store_true",
                   help="close loops (vocabulary tree + LiDAR verification + pose graph); labels move with them")
    add_odometry_option(p)
    add_dope_options(p, defaults=False, unset=CONFIG_DEFAULT)
    add_config_options(p)
    add_dynamic_options(p)
    p.add_argument("--sequential", action="store_true",
                   help="run the detector in the message loop (default: a few images ahead of the pipeline, "
                        "in a process of its own with one torch thread, the camera rendered in another: the "
                        "same results in less wall time)")
    p.add_argument("--json", action="store_true", help="print the report (report.json's content) as JSON on stdout (logs on stderr)")
    add_view_options(p)
    p.set_defaults(func=run)

    p = sub.add_parser("score", help="publish saved runs' maps again (evidence settings) and score the whole map")
    p.add_argument("runs", nargs="+", help="folders written by `dopeslam run`")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="evidence.KEY=VALUE",
                   help="an evidence setting ([evidence] of docs/configuration.md), e.g. evidence.min_observations=3 "
                        "(evidence. may be left out)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="settings file whose [evidence] section applies (e.g. a run's config.toml)")
    p.add_argument("--out", default=None, help="write the scores as JSON here")
    p.add_argument("--json", action="store_true", help="print the scores as JSON on stdout (logs on stderr)")
    p.set_defaults(func=score)


def run(args) -> int:
    import sys

    from stack.config import ConfigError
    from stack.interfaces import ImportPathError, load_detector, odometry_factory, resolve_policy
    from testbed.run import print_summary, run_episode

    try:
        config = config_from_args(args)
    except ConfigError as e:
        return config_error("run", e)
    try:
        policy = resolve_policy(config.store.policy)
        detector = load_detector(config.components.detector) if config.components.detector else None
        odometry = config.components.odometry
        odometry_factory(odometry)
    except ImportPathError as e:
        print(f"dopeslam run: --{e}", file=sys.stderr)  # "--detector 'x:Y': what is wrong"
        return 2
    bad = check_dynamic_options(args, "run")
    if bad is None:
        bad = check_loop_closure(config.loop_closure.enabled, "run")
    if bad is not None:
        return bad
    view, bad = open_view(args, "run")
    if bad is not None:
        return bad
    r = config.run
    from testbed.progress import watching

    try:
        with watching(view):
            report = run_episode(r.scenario, args.out, r.seed, r.light, policy=policy, duration=r.duration,
                                 detector=detector, config=config, faults=args.faults,
                                 store=args.store, odometry=odometry, sequential=args.sequential)
    except ConfigError as e:
        return config_error("run", e)
    except ImportPathError as e:  # the odometry's constructor failed
        print(f"dopeslam run: --{e}", file=sys.stderr)
        return 2
    args.json_result = report  # --json (testbed/cli.py)
    print_summary(report)
    print(f"wrote {args.out}/report.json, config.toml, labels.xlsx, map.png, estimate_tum.txt, groundtruth_tum.txt")
    return 0


def score(args) -> int:
    import sys

    import numpy as np

    from stack.config import ConfigError, parse_assignment, resolve_config
    from stack.evidence import EvidenceConfig
    from testbed.scoring import RunDirError, rescore_run
    from testbed.settings import RunConfig

    try:
        sets = []
        for text in args.settings:
            key, value = parse_assignment(text)
            key = f"evidence.{key}" if key in EvidenceConfig.model_fields else key  # the short form
            if not key.startswith("evidence."):
                raise ConfigError(f"--set {text}: only evidence.KEY settings apply to saved runs; "
                                  f"keys {sorted(EvidenceConfig.model_fields)}")
            sets.append(f"{key}={value}")
        evidence = resolve_config(args.config, sets, model=RunConfig).evidence
    except ConfigError as e:
        return config_error("score", e)
    if args.out:  # the scores never go over a saved run's files
        from testbed.io import check_new_output

        check_new_output(args.out, "--out", force=True, inputs=args.runs)
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
    args.json_result = {"evidence": evidence.model_dump(), "runs": rows}  # --json
    if args.out:
        from testbed.simulate import write_json

        write_json(args.out, {"evidence": evidence.model_dump(), "runs": rows})
    return 0
