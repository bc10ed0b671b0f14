"""``dopeslam scenes``: list the bundled scenarios."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("scenes", help="list the bundled scenarios")
    p.set_defaults(func=run)


def run(args) -> int:
    from sim.scenario import DEFAULT_SCENARIO, bundled_scenarios, load_scenario

    for name in bundled_scenarios():
        sc = load_scenario(name)
        mark = " (default)" if name == DEFAULT_SCENARIO else ""
        print(f"{name}{mark}: {sc.description} [light {sc.light}, {sc.duration:.0f} s, {len(sc.objects)} objects]")
    return 0
