"""``dopeslam loop-closure`` (odometry with and without loop closure on a scenario, no DOPE) and
``dopeslam loop-eval`` (place-recognition precision/recall and closure scoring). The options live
here and the work in ``testbed.loop_closing`` / ``testbed.loop_eval``, imported when the command
runs (building the parser stays light)."""
from __future__ import annotations

import importlib


def _lazy(module: str, name: str = "run_args"):
    """``module.name(args)``, imported on the call; named after it (``__module__``, ``__name__``)."""

    def call(args):
        from testbed.commands.run import check_loop_closure

        bad = check_loop_closure(True, args.command)
        if bad is not None:
            return bad
        return getattr(importlib.import_module(module), name)(args)

    call.__module__, call.__name__, call.__qualname__ = module, name, name
    return call


def register(sub) -> None:
    from testbed.commands.run import add_odometry_option

    p = sub.add_parser("loop-closure", help="LiDAR odometry with and without loop closure on a looping scenario")
    p.add_argument("scenario", nargs="?", default="office_loop", help="bundled name or TOML path")
    p.add_argument("--out", default="out/loop_closure", help="output folder")
    p.add_argument("--seed", type=int, default=None, help="episode seed (default: the scenario's)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    p.add_argument("--vocabulary", default=None, help="vocabulary .npz (default: built from the training scenarios)")
    p.add_argument("--proximity", choices=["fallback", "always", "never"], default=None,
                   help="LiDAR-proximity candidates (default: fallback, when retrieval has none)")
    add_odometry_option(p)
    p.set_defaults(func=_lazy("testbed.loop_closing"))

    e = sub.add_parser("loop-eval", help="place-recognition retrieval precision/recall and loop-closure scores")
    e.add_argument("scenario", nargs="?", default="office_loop_twice", help="bundled name or TOML path")
    e.add_argument("--out", default="out/loop_eval", help="output folder")
    e.add_argument("--seed", type=int, default=None, help="episode seed (default: the scenario's)")
    e.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    e.add_argument("--vocabulary", default=None, help="a vocabulary .npz (default: trained on the first lap)")
    e.add_argument("--branching", type=int, default=10, help="vocabulary tree branching factor")
    e.add_argument("--depth", type=int, default=3, help="vocabulary tree depth")
    e.add_argument("--keep-key-frames", action="store_true", help="save (and reuse) OUT/key_frames.npz")
    e.set_defaults(func=_lazy("testbed.loop_eval"))
