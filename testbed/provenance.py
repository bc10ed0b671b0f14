"""What a run's outputs were made from, for ``report.json``'s ``"provenance"``: the package version,
the git commit (when the code runs from a git checkout; null otherwise), SHA-256 of the detector's
weights and FPR thresholds files and of the scenario's TOML, the seed and the command line."""
from __future__ import annotations

import hashlib
import subprocess
import sys
try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11: the same parser, backported
    import tomli as tomllib
from importlib import metadata
from pathlib import Path

PACKAGE = "dopeslam-testbed"
REPO_ROOT = Path(__file__).resolve().parents[1]


def file_sha256(path) -> str | None:
    """SHA-256 (hex) of a file's bytes; None when there is no such file."""
    if path is None or not Path(path).is_file():
        return None
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def scenario_sha256(path) -> str | None:
    """SHA-256 of a scenario file's bytes followed by those of each file it ``extends`` (so a change
    to a base scenario changes the hash); None when there is no file."""
    if path is None or not Path(path).is_file():
        return None
    h = hashlib.sha256()
    path = Path(path)
    for _ in range(6):  # sim.scenario allows chains of at most 5 files
        data = path.read_bytes()
        h.update(data)
        try:
            parent = tomllib.loads(data.decode("utf-8")).get("extends")
        except (UnicodeDecodeError, tomllib.TOMLDecodeError):
            break
        if not isinstance(parent, str) or not (path.parent / parent).is_file():
            break
        path = path.parent / parent
    return h.hexdigest()


def package_version() -> str | None:
    try:
        return metadata.version(PACKAGE)
    except metadata.PackageNotFoundError:
        return None


def git_commit(root: Path = REPO_ROOT) -> dict | None:
    """``{"commit": sha, "dirty": bool}`` when ``root`` is a git checkout, else None (no git, an
    installed copy, or git failing are all None, never an error)."""
    if not (root / ".git").exists():
        return None
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        if sha.returncode != 0:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": sha.stdout.strip(), "dirty": bool(dirty.stdout.strip()) if dirty.returncode == 0 else None}


def provenance(seed=None, scenario=None, weights=None, thresholds=None, argv=None) -> dict:
    """The ``"provenance"`` of a report. ``scenario``: the scenario's TOML path; ``weights``,
    ``thresholds``: the detector's files (None for a detector without them)."""
    git = git_commit()
    return {
        "package": PACKAGE,
        "version": package_version(),
        "git_commit": git["commit"] if git else None,
        "git_dirty": git["dirty"] if git else None,
        "weights": None if weights is None else str(weights),
        "weights_sha256": file_sha256(weights),
        "fpr_thresholds": None if thresholds is None else str(thresholds),
        "fpr_thresholds_sha256": file_sha256(thresholds),
        "scenario": None if scenario is None else str(scenario),
        "scenario_sha256": scenario_sha256(scenario),
        "seed": seed,
        "command": list(sys.argv if argv is None else argv),
    }


def detector_files(detector) -> tuple[Path | None, Path | None]:
    """(weights, FPR thresholds) files of a detector, where it has them (the bundled DOPE does)."""
    return getattr(detector, "weights_path", None), getattr(detector, "thresholds_path", None)
