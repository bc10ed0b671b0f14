"""``dopeslam test SCENARIO_OR_SUITE... [--seeds 0-9] [--jobs N] [--out DIR] [--junit FILE]
[--baseline DIR [--update-baseline]] [--set key=value] [--json]``: scenario test suites for CI."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("test", help="run scenarios or suites over seeds and check their expectations (JUnit, "
                                    "summary.json, report.html); exit 1 when one fails")
    p.add_argument("targets", nargs="+", metavar="SCENARIO_OR_SUITE",
                   help="a bundled suite (mission, smoke), a suite TOML, a bundled scenario's name or a scenario TOML")
    p.add_argument("--seeds", default=None, help="seeds for every case, e.g. 0-9,20 (default: the suite's, else the "
                                                  "scenario's own seed)")
    p.add_argument("--jobs", type=int, default=1, help="episodes at once")
    p.add_argument("--ray", action="store_true", help="run the episodes on Ray")
    p.add_argument("--ray-address", default=None, help="a Ray cluster's address (with --ray)")
    p.add_argument("--out", default="out/test", help="folder for summary.json, junit.xml, report.html and the runs")
    p.add_argument("--junit", default=None, metavar="FILE", help="also write the JUnit XML here (always OUT/junit.xml)")
    p.add_argument("--baseline", default=None, metavar="DIR", help="an earlier `dopeslam test` output: fail on a change "
                                                                   "for the worse beyond each metric's tolerance")
    p.add_argument("--update-baseline", action="store_true", help="write this run's summary.json into --baseline DIR")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="a run option for every case: duration, light, input, stages, fpr, policy, detector, "
                        "loop_closure, weights")
    p.add_argument("--json", action="store_true", help="print summary.json's content on stdout (logs on stderr)")
    p.set_defaults(func=run)


def run(args) -> int:
    import sys

    from testbed.testing.baseline import BaselineError, load_baseline
    from testbed.testing.runner import print_results, run_plan, update_baseline
    from testbed.testing.suite import SuiteError, load_plan

    def usage(msg: str) -> int:
        print(f"dopeslam test: {msg}", file=sys.stderr)
        return 2

    if args.jobs < 1:
        return usage(f"--jobs: expected a number >= 1, got {args.jobs}")
    if args.update_baseline and not args.baseline:
        return usage("--update-baseline: needs --baseline DIR (where to write it)")
    try:
        plan = load_plan(args.targets, args.seeds, args.settings)
        baseline = None
        if args.baseline and not args.update_baseline:
            baseline = load_baseline(args.baseline)
    except (SuiteError, BaselineError) as e:
        return usage(str(e))
    summary, regressions = run_plan(plan, args.out, jobs=args.jobs, ray=args.ray, ray_address=args.ray_address,
                                    baseline=baseline, junit=args.junit)
    print_results(summary, regressions, sys.stdout)
    if args.update_baseline:
        print(f"baseline written: {update_baseline(summary, args.baseline)}", file=sys.stderr)
    print(f"wrote {args.out}/summary.json, junit.xml, report.html", file=sys.stderr)
    args.json_result = summary  # printed by the CLI with --json
    return 0 if summary["passed"] else 1
