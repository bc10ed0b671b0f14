"""What pyproject.toml declares against what the code needs: the Python range against the stdlib
modules, names and syntax the code uses, and the pins against what pip resolves for
``kiss-icp[all]`` (KISS-ICP's own instruction for its dataloaders), kept in
tests/data/kiss_icp_all_resolution.json so that no test needs the network."""
import ast
import json
import re
from pathlib import Path

import pytest

from helpers import ROOT

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

packaging = pytest.importorskip("packaging")
from packaging.requirements import Requirement  # noqa: E402
from packaging.specifiers import SpecifierSet  # noqa: E402

PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
RESOLUTION = json.loads((ROOT / "tests" / "data" / "kiss_icp_all_resolution.json").read_text())

# stdlib modules and names newer than some Python 3 release: (module, name or None) -> first version
NEW_IN = {
    ("tomllib", None): (3, 11), ("wsgiref.types", None): (3, 11),
    ("typing", "Self"): (3, 11), ("typing", "LiteralString"): (3, 11), ("typing", "Never"): (3, 11),
    ("typing", "assert_never"): (3, 11), ("typing", "reveal_type"): (3, 11), ("typing", "TypeVarTuple"): (3, 11),
    ("typing", "Unpack"): (3, 11), ("typing", "NotRequired"): (3, 11), ("typing", "Required"): (3, 11),
    ("typing", "override"): (3, 12), ("typing", "TypeAliasType"): (3, 12),
    ("enum", "StrEnum"): (3, 11), ("datetime", "UTC"): (3, 11), ("hashlib", "file_digest"): (3, 11),
    ("asyncio", "TaskGroup"): (3, 11), ("contextlib", "chdir"): (3, 11), ("itertools", "batched"): (3, 12),
}
# conflicts with kiss-icp[all]'s resolution that are declared on purpose: pip refuses the pair
# instead of installing a version the code cannot run on (docs/install.md says so)
DECLARED_CONFLICTS = {
    "rosbags": "testbed/bags/writer.py imports rosbags.interfaces.Qos and rosbag2.StoragePlugin (0.10.9+)",
}


def python_floor() -> tuple[int, int]:
    m = re.fullmatch(r">=\s*3\.(\d+)", PROJECT["requires-python"].strip())
    assert m, f"requires-python {PROJECT['requires-python']!r}: expected '>=3.N'"
    return 3, int(m.group(1))


def sources():
    for folder in ("stack", "sim", "testbed"):
        yield from sorted((ROOT / folder).rglob("*.py"))


def _guarded(node, parents) -> bool:
    """Whether ``node`` sits in a ``try`` whose handlers catch an ImportError."""
    for p in parents.get(id(node), []):
        if isinstance(p, ast.Try):
            for h in p.handlers:
                names = {getattr(n, "id", getattr(n, "attr", None)) for n in
                         ([h.type] if not isinstance(h.type, ast.Tuple) else h.type.elts)} if h.type else {None}
                if names & {"ImportError", "ModuleNotFoundError", "Exception", None}:
                    return True
    return False


def newer_uses(path: Path, floor: tuple[int, int]) -> list[str]:
    src = path.read_text(encoding="utf-8")
    tree = ast.parse(src)
    parents: dict[int, list] = {}
    stack = [(tree, [])]
    while stack:
        node, chain = stack.pop()
        parents[id(node)] = chain
        for child in ast.iter_child_nodes(node):
            stack.append((child, [node, *chain]))
    found = []
    for node in ast.walk(tree):
        hits = []
        if isinstance(node, ast.Import):
            hits = [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            hits = [(node.module, None)] + [(node.module, a.name) for a in node.names]
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            hits = [(node.value.id, node.attr)]
        for key in hits:
            version = NEW_IN.get(key)
            if version and version > floor and not _guarded(node, parents):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {'.'.join(k for k in key if k)} "
                             f"(Python {version[0]}.{version[1]}+) without a fallback")
    return found


def test_code_runs_on_the_declared_python_floor():
    floor = python_floor()
    problems = []
    for path in sources():
        try:  # syntax newer than the floor (except*, type statements, ...) does not parse
            ast.parse(path.read_text(encoding="utf-8"), feature_version=floor)
        except SyntaxError as exc:
            problems.append(f"{path.relative_to(ROOT)}:{exc.lineno}: syntax newer than Python {floor[0]}.{floor[1]}")
        problems += newer_uses(path, floor)
    assert not problems, "\n".join(problems)


def test_the_scan_finds_an_unguarded_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import tomllib\nfrom typing import Self\n")
    good = tmp_path / "good.py"
    good.write_text("try:\n    import tomllib\nexcept ModuleNotFoundError:\n    import tomli as tomllib\n")
    global ROOT
    root, ROOT = ROOT, tmp_path
    try:
        assert len(newer_uses(bad, (3, 10))) == 2 and newer_uses(good, (3, 10)) == []
        assert newer_uses(bad, (3, 11)) == []
    finally:
        ROOT = root


def test_tomli_is_declared_where_tomllib_is_missing():
    reqs = [Requirement(r) for r in PROJECT["dependencies"]]
    tomli = [r for r in reqs if r.name == "tomli"]
    assert tomli and tomli[0].marker is not None
    assert tomli[0].marker.evaluate({"python_version": "3.10"})
    assert not tomli[0].marker.evaluate({"python_version": "3.11"})


def _ours() -> dict[str, Requirement]:
    reqs = [Requirement(r) for r in PROJECT["dependencies"]]
    return {r.name.lower().replace("_", "-"): r for r in reqs if r.marker is None or r.marker.evaluate()}


def test_pins_agree_with_kiss_icp_all_or_declare_the_conflict():
    resolved = RESOLUTION["resolved"]
    ours = _ours()
    shared = sorted(set(ours) & set(resolved))
    assert {"kiss-icp", "numpy", "rosbags", "pydantic"} <= set(shared)  # the data still covers what matters
    unexpected = []
    for name in shared:
        version = resolved[name]
        if ours[name].specifier.contains(version, prereleases=True):
            assert name not in DECLARED_CONFLICTS, f"{name}: declared a conflict that no longer exists"
        elif name not in DECLARED_CONFLICTS:
            unexpected.append(f"{name}: kiss-icp[all] resolves {version}, we declare {ours[name].specifier}")
    assert not unexpected, "\n".join(unexpected)
    docs = (ROOT / "docs" / "install.md").read_text()
    for name in DECLARED_CONFLICTS:
        assert name in docs and resolved[name] in docs, f"docs/install.md should explain the {name} conflict"


def test_rosbags_floor_refuses_the_release_without_qos():
    pin = next(r for r in RESOLUTION["requires"]["ouster-sdk"] if r.startswith("rosbags"))
    assert Requirement(pin).specifier == SpecifierSet("==0.9.23")
    assert not _ours()["rosbags"].specifier.contains("0.9.23")
    assert "Qos" in (ROOT / "testbed" / "bags" / "writer.py").read_text()


def test_every_cap_has_a_reason():
    lines = (ROOT / "pyproject.toml").read_text().splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith("dependencies = ["))
    for ln in lines[start + 1:]:
        if ln.startswith("]"):
            break
        req = Requirement(ln.split("#")[0].strip().strip(",").strip('"'))
        capped = any(s.operator in ("<", "<=", "==", "~=") for s in req.specifier)
        if capped:
            assert "#" in ln and "cap" in ln.split("#", 1)[1], f"{req.name}: an upper bound needs a comment saying why"


def test_gtsam_is_an_extra_that_loop_closure_names():
    ours = _ours()
    assert "gtsam" not in ours
    assert any(Requirement(r).name == "gtsam" for r in PROJECT["optional-dependencies"]["loops"])
    from stack.loops.closure import GTSAM_MISSING

    assert "pip install 'dopeslam-testbed[loops]'" in GTSAM_MISSING


def test_loops_caps_numpy_where_only_gtsam_4_2_has_a_wheel():
    """gtsam 4.2, the newest release with a wheel for Python 3.10, is built against NumPy 1: with NumPy 2
    ``gtsam.Pose3(np.eye(4))`` segfaults. gtsam 4.3 (wheels for 3.11+) is built against NumPy 2."""
    reqs = [Requirement(r) for r in PROJECT["optional-dependencies"]["loops"]]

    def numpy_specs(python):
        env = {"python_version": python, "extra": "loops"}
        return [r.specifier for r in reqs if r.name == "numpy" and (r.marker is None or r.marker.evaluate(env))]

    assert any(not s.contains("2.0.0") for s in numpy_specs("3.10"))
    assert all(s.contains("2.0.0") for s in numpy_specs("3.11"))
    assert _ours()["numpy"].specifier.contains("1.26.4")  # the core allows what the cap leaves
