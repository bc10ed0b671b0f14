"""Test suites: which scenarios run, over which seeds, with which options, and what must hold.

A suite is a TOML file with ``[[scenarios]]`` entries (``testbed/suites/*.toml`` are bundled; see
docs/testing.md); a scenario file on its own is a suite of one, with its own ``[expect]`` table.
Everything is checked before anything runs: errors name the file and the key.
"""
from __future__ import annotations

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11: the same parser, backported
    import tomli as tomllib
from dataclasses import dataclass, field
from pathlib import Path

from stack.errors import DopeSlamError
from stack.io import read_user_text
from testbed.testing.cells import Cell, parse_seeds
from testbed.testing.expect import ExpectError, Expectation, Outcome, evaluate_all, parse_expectations
from testbed.testing.options import RUN_OPTIONS, OptionError, check_options, check_setting, coerce

SUITES_DIR = Path(__file__).resolve().parent.parent / "suites"
SUITE_KEYS = {"name", "description", "seeds", "options", "expect", "scenarios", "baseline_tolerance"}
ENTRY_KEYS = {"scenario", "id", "seeds", "options", "expect"}


class SuiteError(DopeSlamError, ValueError):
    """A suite, scenario or command-line value that cannot be used (one line: file, key, what was expected)."""


@dataclass
class Case:
    id: str
    scenario: str  # a bundled name or a path
    seeds: list[int]
    options: dict
    expectations: list[Expectation]
    min_pass_rate: float = 1.0
    source: str = ""

    def cells(self) -> list[Cell]:
        return [Cell(self.scenario, s, dict(self.options)) for s in self.seeds]


@dataclass
class Plan:
    name: str
    cases: list[Case]
    tolerances: dict = field(default_factory=dict)  # baseline tolerance per metric path


def bundled_suites() -> list[str]:
    return sorted(p.stem for p in SUITES_DIR.glob("*.toml"))


def _scenario(name: str, where: str):
    from sim.scenario import ScenarioError, load_scenario

    try:
        return load_scenario(name)
    except ScenarioError as e:
        raise SuiteError(f"{where}{e}") from None


def _seeds(value, where: str) -> list[int]:
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return [value]
    if isinstance(value, list) and value and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value):
        return list(dict.fromkeys(value))
    if isinstance(value, str):
        try:
            return parse_seeds(value)
        except ValueError as e:
            raise SuiteError(f"{where}: {e}") from None
    raise SuiteError(f"{where}: expected seeds such as \"0-9,20\" or [0, 1], got {value!r}")


def _case(scenario: str, entry: dict, defaults: dict, where: str, base: Path | None) -> Case:
    if base is not None and scenario.endswith(".toml") and not Path(scenario).is_absolute():
        scenario = str(base / scenario)
    sc = _scenario(scenario, "" if base is None else f"{where}: ")
    options = {**defaults.get("options", {}), **entry.get("options", {})}
    try:
        options = check_options(options)
    except OptionError as e:
        raise SuiteError(f"{where}: {e}") from None
    job = options.get("job", "run")
    table = {**sc.expect, **defaults.get("expect", {}), **entry.get("expect", {})}
    try:
        exps, rate = parse_expectations(table, job, sc.object_names)
    except ExpectError as e:
        src = sc.source if not (defaults.get("expect") or entry.get("expect")) else where
        raise SuiteError(f"{src}: {e}") from None
    seeds = entry.get("seeds", defaults.get("seeds"))
    seeds = [sc.seed] if seeds is None else _seeds(seeds, f"{where}: field 'seeds'")
    name = entry.get("id") or Path(scenario).stem + ("" if job == "run" else f"-navigate-{options['object']}")
    return Case(str(name), scenario, seeds, options, exps, rate, source=sc.source)


def _table(value, where: str) -> dict:
    if not isinstance(value, dict):
        raise SuiteError(f"{where}: expected a table, got {value!r}")
    return value


def load_suite(path: Path) -> Plan:
    text = read_user_text(path, SuiteError, "a suite TOML file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SuiteError(f"{path}: not valid TOML: {e}") from None
    unknown = set(data) - SUITE_KEYS
    if unknown:
        raise SuiteError(f"{path}: field '{sorted(unknown)[0]}': not a suite field; fields: {', '.join(sorted(SUITE_KEYS))}")
    entries = data.get("scenarios")
    if not isinstance(entries, list) or not entries:
        raise SuiteError(f"{path}: field 'scenarios': expected one or more [[scenarios]] tables")
    defaults = {k: _table(data[k], f"{path}: field '{k}'") for k in ("options", "expect") if k in data}
    if "seeds" in data:
        defaults["seeds"] = data["seeds"]
    cases = []
    for i, entry in enumerate(entries):
        where = f"{path}: scenarios.{i}"
        entry = _table(entry, where)
        bad = set(entry) - ENTRY_KEYS
        if bad:
            raise SuiteError(f"{where}: field '{sorted(bad)[0]}': not an entry field; fields: {', '.join(sorted(ENTRY_KEYS))}")
        if not isinstance(entry.get("scenario"), str):
            raise SuiteError(f"{where}: field 'scenario': expected a bundled scenario's name or a TOML path")
        for k in ("options", "expect"):
            if k in entry:
                _table(entry[k], f"{where}: field '{k}'")
        cases.append(_case(entry["scenario"], entry, defaults, where, path.parent))
    tol = _table(data.get("baseline_tolerance", {}), f"{path}: field 'baseline_tolerance'")
    for k, v in tol.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
            raise SuiteError(f"{path}: field 'baseline_tolerance.{k}': expected a number >= 0, got {v!r}")
    return Plan(str(data.get("name", path.stem)), cases, {k: float(v) for k, v in tol.items()})


def is_suite_file(path: Path) -> bool:
    """A suite lists ``[[scenarios]]``; a scenario has a ``[room]`` (or ``extends`` another)."""
    try:
        data = tomllib.loads(path.read_bytes().decode("utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    return "scenarios" in data or not ("room" in data or "extends" in data)


def load_plan(targets: list[str], seeds: str | None = None, settings: list[str] | None = None) -> Plan:
    """Suites and scenarios named on the command line -> one plan. ``seeds`` (``"0-9,20"``) replaces
    every case's seeds; ``settings`` (``key=value``) set a run option on every run case."""
    plans = []
    for t in targets:
        p = Path(t)
        if (SUITES_DIR / f"{t}.toml").exists() and not p.exists():
            plans.append(load_suite(SUITES_DIR / f"{t}.toml"))
        elif p.suffix == ".toml" and p.exists() and is_suite_file(p):
            plans.append(load_suite(p))
        else:
            from sim.scenario import ScenarioError, bundled_scenarios, resolve_path

            try:
                resolve_path(t)
            except ScenarioError:
                raise SuiteError(f"{t}: no such suite or scenario (bundled suites: {', '.join(bundled_suites())}; "
                                 f"scenarios: {', '.join(bundled_scenarios())})") from None
            case = _case(t, {}, {}, t, None)
            plans.append(Plan(case.id, [case]))
    cases = [c for p in plans for c in p.cases]
    if seeds is not None:
        try:
            override = parse_seeds(seeds)
        except ValueError as e:
            raise SuiteError(f"--seeds: {e}") from None
        for c in cases:
            c.seeds = list(override)
    for s in settings or []:
        key, sep, value = s.partition("=")
        key = key.strip()
        if not sep or (key not in RUN_OPTIONS and "." not in key):
            raise SuiteError(f"--set {s!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(RUN_OPTIONS))} "
                             f"or a stack setting SECTION.KEY")
        try:
            v = check_setting(key, value.strip()) if "." in key else coerce(key, value, RUN_OPTIONS)
        except OptionError as e:
            raise SuiteError(f"--set: {e}") from None
        for c in cases:
            if c.options.get("job", "run") == "run":
                c.options[key] = v
    seen: dict[str, int] = {}
    for c in cases:  # ids unique: they name JUnit test cases and baseline rows
        if c.id in seen:
            seen[c.id] += 1
            c.id = f"{c.id}-{seen[c.id]}"
        else:
            seen[c.id] = 1
    tol = {k: v for p in plans for k, v in p.tolerances.items()}
    return Plan("+".join(p.name for p in plans), cases, tol)


# --------------------------------------------------------------------------------------------- results

def evaluate_case(case: Case, results: list[dict]) -> dict:
    """One case's results (one per seed, in order) checked: the case's part of summary.json."""
    from testbed.testing.baseline import metrics_of

    cells = []
    for seed, r in zip(case.seeds, results):
        outcomes: list[Outcome] = evaluate_all(case.expectations, r["report"]) if r["status"] == "ok" else []
        cells.append({"seed": seed, "status": r["status"], "error": r["error"], "out_dir": r["out_dir"],
                      "passed": r["status"] == "ok" and all(o.ok for o in outcomes),
                      "expectations": [o.as_dict() for o in outcomes],
                      "metrics": metrics_of(r["report"], case) if r["status"] == "ok" else {},
                      "wall_seconds": (r["report"] or {}).get("wall_seconds")})
    n_pass = sum(c["passed"] for c in cells)
    rate = n_pass / len(cells) if cells else 0.0
    passed = rate >= case.min_pass_rate - 1e-12 and not any(c["status"] != "ok" for c in cells)
    for c in cells:
        c["tolerated"] = passed and not c["passed"]
    return {"id": case.id, "scenario": case.scenario, "options": case.options, "seeds": case.seeds,
            "expectations": [str(e) for e in case.expectations], "min_pass_rate": case.min_pass_rate,
            "pass_rate": rate, "passed": passed, "cells": cells}
