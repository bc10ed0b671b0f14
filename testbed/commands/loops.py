"""``dopeslam loop-closure`` (odometry with and without loop closure on a scenario, no DOPE) and
``dopeslam loop-eval`` (place-recognition precision/recall and closure scoring)."""
from __future__ import annotations


def register(sub) -> None:
    from testbed import loop_closing, loop_eval

    p = sub.add_parser("loop-closure", help="LiDAR odometry with and without loop closure on a looping scenario")
    loop_closing.add_arguments(p)
    p.set_defaults(func=loop_closing.run_args)
    e = sub.add_parser("loop-eval", help="place-recognition retrieval precision/recall and loop-closure scores")
    loop_eval.add_arguments(e)
    e.set_defaults(func=loop_eval.run_args)
