"""Running scenario x seed cells: ``testbed.matrix`` (parallel, Ray) where it is installed, else the
same contract sequentially here. A cell's result: {"cell", "status" ("ok"|"error"), "error",
"report", "out_dir"}."""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

from testbed.matrix import parse_seeds  # noqa: F401  (one seed syntax everywhere)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Cell:
    scenario: str
    seed: int
    options: dict = field(default_factory=dict)


def cell_dir(out_dir: Path, cell) -> Path:
    name = Path(str(cell.scenario)).stem
    tag = "_".join(f"{k}-{v}" for k, v in sorted(cell.options.items()) if k != "job") if cell.options else ""
    tag = re.sub(r"[^A-Za-z0-9_.-]+", "_", tag)[:80]
    return Path(out_dir) / (f"{name}__{tag}" if tag else name) / f"seed{cell.seed}"


def run_sequential(cells, out_dir, progress: bool = True) -> list[dict]:
    """Each cell in its own process (``testbed.testing.worker``), one after the other: a crash in
    one (the renderer's, say) is that cell's error and the others still run."""
    import json
    import subprocess
    import sys
    import tempfile

    results = []
    for i, cell in enumerate(cells):
        d = cell_dir(Path(out_dir), cell)
        d.parent.mkdir(parents=True, exist_ok=True)
        if progress:
            log.info("cell %d/%d: %s seed %d %s", i + 1, len(cells), cell.scenario, cell.seed, cell.options or "")
        with tempfile.TemporaryDirectory(prefix="dopeslam_cell_") as tmp:
            spec, result = Path(tmp) / "spec.json", Path(tmp) / "result.json"
            spec.write_text(json.dumps({"scenario": cell.scenario, "seed": cell.seed, "options": cell.options,
                                        "out_dir": str(d), "result": str(result)}))
            sys.stdout.flush()
            proc = subprocess.run([sys.executable, "-m", "testbed.testing.worker", str(spec)])
            data = json.loads(result.read_text()) if result.is_file() else {}
            if proc.returncode == 0 and "report" in data:
                results.append({"cell": cell, "status": "ok", "error": None, "report": data["report"],
                                "out_dir": str(d)})
                continue
            why = data.get("error") or (f"killed by signal {-proc.returncode}" if proc.returncode < 0
                                        else f"exit status {proc.returncode}")
            results.append({"cell": cell, "status": "error", "error": str(why)[:2000], "report": None,
                            "out_dir": str(d)})
    return results


def _plain(report: dict) -> dict:
    return {k: v for k, v in report.items() if not k.startswith("_")}


def run_cells(cells, out_dir, jobs: int = 1, ray: bool = False, ray_address=None, progress: bool = True) -> list[dict]:
    """Run ``dopeslam run`` cells through ``testbed.matrix`` when it is there; navigate cells (and
    everything when it is not) here, one after the other. Results in the order of ``cells``."""
    try:
        from testbed import matrix
    except ImportError:
        matrix = None
    nav = [i for i, c in enumerate(cells) if c.options.get("job") == "navigate"]
    runs = [i for i, c in enumerate(cells) if c.options.get("job") != "navigate"]
    results: list[dict | None] = [None] * len(cells)
    if matrix is not None and runs:
        mcells = [matrix.Cell(scenario=cells[i].scenario, seed=cells[i].seed, options=dict(cells[i].options))
                  for i in runs]
        for i, r in zip(runs, matrix.run_cells(mcells, out_dir, jobs=jobs, ray=ray, ray_address=ray_address,
                                               progress=progress)):
            results[i] = {**r, "cell": cells[i]}
    elif runs:
        for i, r in zip(runs, run_sequential([cells[i] for i in runs], out_dir, progress)):
            results[i] = r
    for i, r in zip(nav, run_sequential([cells[i] for i in nav], out_dir, progress)):
        results[i] = r
    return results
