"""The monocular topological-map system: ``dopeslam navigate OBJECT [SCENARIO]``, ``dopeslam navigate-batch``,
``dopeslam compare [SCENARIO]``, ``dopeslam pose-eval`` and ``dopeslam hog-detector train|eval|table``."""
from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("navigate", help="monocular topological map: localise by retrieval, plan, drive to the node holding OBJECT")
    p.add_argument("object", help="an object's name or class in the scenario")
    p.add_argument("scenario", nargs="?", default=None, help="bundled name or TOML path (default: the default scenario)")
    p.add_argument("--out", default="out/navigate")
    p.add_argument("--seed", type=int, default=0, help="perturbs the start pose and drives the sensor noise")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="simulated time limit (default: 30 s + 2.5x the route's length at the driving speed)")
    p.add_argument("--wheels-only", action="store_true",
                   help="dead reckoning between fixes from the wheel odometry alone (default: its travel with the gyro's heading)")
    p.set_defaults(func=_navigate)

    b = sub.add_parser("navigate-batch", help="seeded navigation runs per scenario, the object cycling through those the map holds")
    b.add_argument("--scenarios", default="experiment3_columns,shelf_corridor,office_loop_twice",
                   help="comma-separated (default: %(default)s)")
    b.add_argument("--seeds", default="0-9", help="N or N-M (default: %(default)s)")
    b.add_argument("--out", default="out/topomap/navigate")
    b.add_argument("--wheels-only", action="store_true", help="dead reckoning from the wheel odometry alone")
    b.set_defaults(func=_navigate_batch)

    c = sub.add_parser("compare", help="DOPESLAM and the monocular semantic topological map on the same episodes, lit and dark")
    c.add_argument("scenario", nargs="?", default=None, help="bundled name or TOML path (default: the default scenario)")
    c.add_argument("--out", default="out/compare")
    c.add_argument("--seeds", default=None, help="comma-separated episode seeds (default: the scenario's seed)")
    c.add_argument("--duration", type=float, default=None)
    c.set_defaults(func=_compare)

    e = sub.add_parser("pose-eval", help="monocular pose estimation, ORPE vs TRPE vs Grunert P3P, on the scenario streams")
    e.add_argument("--scenarios", default="experiment3_columns,shelf_corridor", help="comma-separated (default: %(default)s)")
    e.add_argument("--runs", type=int, default=100, help="RANSAC seeds per method (default: %(default)s)")
    e.add_argument("--out", type=Path, default=Path("out/topomap/pose"))
    e.add_argument("--table", type=Path, default=None, help="print the tables of an existing pose_eval.json")
    e.set_defaults(func=_pose_eval)

    h = sub.add_parser("hog-detector", help="train or evaluate the colour-verified HOG detector of the topological map")
    hs = h.add_subparsers(dest="hog_command", required=True, metavar="ACTION")
    data_help = "DOPE data shards folder (default: runs/data/rgbd_v1)"
    t = hs.add_parser("train", help="train the HOG root filters and colour models on the data shards")
    t.add_argument("--data", type=Path, default=None, help=data_help)
    t.add_argument("--max-images", type=int, default=None)
    t.add_argument("--mining-rounds", type=int, default=1, help="hard-negative mining rounds (default: %(default)s)")
    t.add_argument("--mining-images", type=int, default=200, help="images mined per round (default: %(default)s)")
    t.add_argument("--seed", type=int, default=0)
    v = hs.add_parser("eval", help="VOC AP per class, with and without the colour step (Fig. 20 / Table 4)")
    v.add_argument("--data", type=Path, default=None, help=data_help)
    v.add_argument("--out", type=Path, default=Path("out/topomap/detector"))
    v.add_argument("--max-images", type=int, default=None)
    v.add_argument("--no-streams", action="store_true", help="the held-out shards only, not the scenario streams")
    tb = hs.add_parser("table", help="print the tables of an existing detector.json")
    tb.add_argument("report", type=Path, metavar="DETECTOR_JSON")
    h.set_defaults(func=_hog_detector)


def _pose_eval(args) -> int:
    from testbed.topomap.pose_eval import run_args

    return _guarded("pose-eval", run_args, args)


def _hog_detector(args) -> int:
    from testbed.topomap.detector import run_args

    return _guarded("hog-detector", run_args, args)


def _guarded(command: str, func, args) -> int:
    """Run ``func(args)``; a bad input is one line on stderr and exit status 2."""
    import sys

    from testbed.topomap import InputError

    try:
        return func(args)
    except InputError as exc:
        print(f"dopeslam {command}: {exc}", file=sys.stderr)
        return 2


def _navigate(args) -> int:
    from testbed.topomap.navigate import main_args

    return _guarded("navigate", main_args, args)


def _navigate_batch(args) -> int:
    from testbed.topomap.navigate import batch_args

    return _guarded("navigate-batch", batch_args, args)


def _compare(args) -> int:
    from testbed.topomap.compare import main_args

    return main_args(args)
