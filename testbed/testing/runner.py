"""Run a plan: every case x seed, expectations checked, the baseline compared; writes
``summary.json``, ``junit.xml`` and ``report.html`` in the output folder."""
from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

from testbed.testing.baseline import compare
from testbed.testing.cells import run_cells
from testbed.testing.junit import write_junit
from testbed.testing.report_html import write_html
from testbed.testing.suite import Plan, evaluate_case

log = logging.getLogger(__name__)


def _write_json(path: Path, data) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str))
    os.replace(tmp, path)


def run_plan(plan: Plan, out_dir: str | Path, jobs: int = 1, ray: bool = False, ray_address=None,
             baseline: dict | None = None, junit: str | Path | None = None) -> tuple[dict, list[dict]]:
    """Returns (summary, regressions). ``baseline``: an earlier summary (``load_baseline``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cells, spans = [], []
    for case in plan.cases:
        spans.append((len(cells), len(cells) + len(case.seeds)))
        cells.extend(case.cells())
    t0 = time.perf_counter()
    results = run_cells(cells, out / "runs", jobs=jobs, ray=ray, ray_address=ray_address)
    cases = [evaluate_case(case, results[a:b]) for case, (a, b) in zip(plan.cases, spans)]
    summary = {"name": plan.name, "wall_seconds": time.perf_counter() - t0, "cases": cases,
               "baseline_tolerance": plan.tolerances}
    regressions = compare(summary, baseline, plan.tolerances, plan.cases) if baseline is not None else []
    summary["regressions"] = regressions
    summary["passed"] = all(c["passed"] for c in cases) and not regressions
    _write_json(out / "summary.json", summary)
    write_junit(out / "junit.xml", summary, regressions)
    if junit is not None and Path(junit).resolve() != (out / "junit.xml").resolve():
        write_junit(junit, summary, regressions)
    write_html(out / "report.html", summary)
    return summary, regressions


def update_baseline(summary: dict, folder: str | Path) -> Path:
    """Write ``summary`` as the baseline in ``folder`` (its summary.json; deltas dropped)."""
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    clean = json.loads(json.dumps(summary, default=str))
    for case in clean["cases"]:
        for cell in case["cells"]:
            cell.pop("deltas", None)
    clean.pop("regressions", None)
    _write_json(d / "summary.json", clean)
    return d / "summary.json"


def print_results(summary: dict, regressions: list[dict], stream) -> None:
    from testbed.testing.baseline import regression_message
    from testbed.testing.expect import Outcome

    for case in summary["cases"]:
        for cell in case["cells"]:
            tag = "PASS" if cell["passed"] else ("TOLERATED" if cell.get("tolerated") else
                                                 ("ERROR" if cell["status"] != "ok" else "FAIL"))
            print(f"{tag:<9} {case['id']} seed {cell['seed']}", file=stream)
            if cell["status"] != "ok":
                print(f"          {cell['error']}", file=stream)
            for o in cell["expectations"]:
                if not o["ok"]:
                    print(f"          {Outcome(**o).message()}", file=stream)
        if case["min_pass_rate"] < 1:
            print(f"          {case['id']}: {case['pass_rate']:.0%} of seeds pass (needs {case['min_pass_rate']:.0%})",
                  file=stream)
    for r in regressions:
        print(f"REGRESSED {r['case']} seed {r['seed']}: {regression_message(r)}", file=stream)
    n = sum(len(c["cells"]) for c in summary["cases"])
    ok = sum(cell["passed"] or bool(cell.get("tolerated")) for c in summary["cases"] for cell in c["cells"])
    print(f"{summary['name']}: {'PASS' if summary['passed'] else 'FAIL'} ({ok}/{n} runs hold, "
          f"{sum(c['passed'] for c in summary['cases'])}/{len(summary['cases'])} cases; "
          f"{summary['wall_seconds']:.0f} s)", file=stream)
