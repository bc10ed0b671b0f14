"""The topological-map paper's system: ``dopeslam navigate OBJECT [SCENARIO] --out DIR --seed N`` and
``dopeslam compare [SCENARIO] --out DIR``."""
from __future__ import annotations


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

    c = sub.add_parser("compare", help="DOPESLAM and the monocular semantic topological map on the same episodes, lit and dark")
    c.add_argument("scenario", nargs="?", default=None, help="bundled name or TOML path (default: the default scenario)")
    c.add_argument("--out", default="out/compare")
    c.add_argument("--seeds", default=None, help="comma-separated episode seeds (default: the scenario's seed)")
    c.add_argument("--duration", type=float, default=None)
    c.set_defaults(func=_compare)


def _navigate(args) -> int:
    from testbed.topomap.navigate import main_args

    return main_args(args)


def _compare(args) -> int:
    from testbed.topomap.compare import main_args

    return main_args(args)
