"""JUnit XML from a ``dopeslam test`` summary: one testcase per scenario x seed, one ``<failure>``
per unmet expectation (measured value, bound, margin) or regression, ``<error>`` for a run that
did not finish."""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

from testbed.testing.baseline import regression_message
from testbed.testing.expect import Outcome


def _testcases(summary: dict, regressions: list[dict]):
    regs: dict[tuple[str, int], list[dict]] = {}
    for r in regressions:
        regs.setdefault((r["case"], r["seed"]), []).append(r)
    for case in summary["cases"]:
        for cell in case["cells"]:
            tc = ET.Element("testcase", classname=f"{summary['name']}.{case['id']}", name=f"{case['id']} seed {cell['seed']}",
                            time=f"{cell.get('wall_seconds') or 0.0:.3f}")
            failures = 0
            if cell["status"] != "ok":
                e = ET.SubElement(tc, "error", message=str(cell["error"]).splitlines()[0][:500], type="run")
                e.text = str(cell["error"])
            unmet = [Outcome(**o) for o in cell["expectations"] if not o["ok"]]
            if cell.get("tolerated"):
                out = ET.SubElement(tc, "system-out")
                out.text = (f"tolerated: the case passes {case['pass_rate']:.0%} of its seeds (min_pass_rate "
                            f"{case['min_pass_rate']:.0%}); unmet here:\n" + "\n".join(o.message() for o in unmet))
            else:
                for o in unmet:
                    f = ET.SubElement(tc, "failure", message=o.message(), type="expectation")
                    f.text = o.message()
                    failures += 1
            for r in regs.get((case["id"], cell["seed"]), []):
                f = ET.SubElement(tc, "failure", message="regression: " + regression_message(r), type="regression")
                f.text = regression_message(r)
                failures += 1
            yield tc, failures, cell["status"] != "ok"


def write_junit(path: str | Path, summary: dict, regressions: list[dict] | None = None) -> None:
    suites = ET.Element("testsuites", name="dopeslam test")
    suite = ET.SubElement(suites, "testsuite", name=summary["name"])
    n = fails = errors = 0
    total = 0.0
    for tc, f, err in _testcases(summary, regressions or []):
        suite.append(tc)
        n += 1
        fails += f > 0
        errors += err
        total += float(tc.get("time"))
    for el in (suite, suites):
        el.set("tests", str(n))
        el.set("failures", str(fails))
        el.set("errors", str(errors))
        el.set("time", f"{total:.3f}")
    ET.indent(suites)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    ET.ElementTree(suites).write(tmp, encoding="utf-8", xml_declaration=True)
    os.replace(tmp, path)
