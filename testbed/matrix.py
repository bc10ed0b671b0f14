"""The matrix runner: many seeded episodes ("cells"), run in local processes or as Ray tasks.

A :class:`Cell` is a scenario, a seed and options (``dopeslam run``'s short names such as
``light``, ``input``, ``stages``, or any config key ``section.key``, see ``docs/configuration.md``).
Every cell resolves to one :class:`testbed.settings.RunConfig` and is keyed by :func:`cell_key`: a
hash of the scenario file's content, the seed, the resolved config, the detector's weights and
thresholds files and the package version. A cell's outputs live in ``OUT/cells/<key>/``; a cell
whose folder holds a complete ``report.json`` is not run again (resume). A cell with the option
``job = "perception-cache"`` builds one episode's perception cache for the labelling environment
instead (``dopeslam evaluate-policy --jobs N``), keyed by that cache's identity.

Backends (:func:`run_cells`):

* processes (default): each cell in a fresh ``python`` process, ``jobs`` at a time, torch
  single-threaded in each. A cell that raises, or whose process dies, is retried once, then it is an
  error row with its message; the other cells go on.
* Ray (``ray=True``: a local Ray runtime; ``ray_address``: an existing cluster): each cell is a Ray
  task asking for one CPU. It runs in a temporary folder on its node and returns its report (and, with
  ``collect_files``, its output folder as a tar archive) to the driver, which writes them under
  ``OUT/cells/<key>/``.

Whatever the backend or the number of workers, a cell's report is computed by the same function from
the same inputs, so the rows are the same (timing columns aside, :data:`VOLATILE`).
"""
from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import re
import subprocess
import sys
import tarfile
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from stack.errors import DopeSlamError

log = logging.getLogger(__name__)

# report.json scalars that differ between runs of the same cell: wall-clock timings and where/how it ran
VOLATILE = re.compile(r"^(wall_seconds|real_time_factor|time_split_s\..*|timings?\..*|.*_hz|.*\.fps|fps|"
                      r"provenance\.(command|git_commit|git_dirty|weights|fpr_thresholds|scenario))$")
RETRIES = 1  # a failed cell runs once more before it becomes an error row
SHORT_KEYS = {"loop_closure": "loop_closure.enabled"}  # option names of `dopeslam test` cases
JOBS = ("run", "perception-cache")  # what a cell runs (its option "job"; see cell_job)


class MatrixError(DopeSlamError, ValueError):
    """A seed list, grid or cell option that cannot be used; the message names the part."""


class SeedSyntaxError(MatrixError):
    pass


def parse_seeds(text) -> list[int]:
    """``"0-9,20,31-35"`` -> the seeds in that order, duplicates dropped. An int is one seed."""
    if isinstance(text, int) and not isinstance(text, bool):
        text = str(text)
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        m = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if not m or (m.group(2) is not None and int(m.group(2)) < int(m.group(1))):
            raise SeedSyntaxError(f"seeds: expected non-negative integers and ranges such as 0-9,20,31-35, "
                                  f"got {part!r}")
        lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
        if hi - lo > 100_000:
            raise SeedSyntaxError(f"seeds: range {part!r} has more than 100000 seeds")
        seen = set(seeds)
        seeds.extend(s for s in range(lo, hi + 1) if s not in seen)
    return seeds


@dataclass(frozen=True)
class Cell:
    scenario: str
    seed: int
    options: dict = field(default_factory=dict, hash=False)

    def label(self) -> str:
        opts = " ".join(f"{k}={v}" for k, v in sorted(self.options.items()))
        return f"{Path(str(self.scenario)).stem} seed {self.seed}" + (f" {opts}" if opts else "")


# ----------------------------------------------------------------------------------------- resolution

def cell_job(cell: Cell) -> str:
    """What the cell runs: ``run`` (a scored episode, the default) or ``perception-cache`` (the
    labelling environment's perception cache of one episode; the other options are the environment's
    keyword arguments)."""
    job = cell.options.get("job", "run")
    if job not in JOBS:
        raise MatrixError(f"cell option 'job': expected one of {list(JOBS)}, got {job!r}")
    return job


def _env_kwargs(cell: Cell) -> dict:
    return {k: v for k, v in cell.options.items() if k != "job"}


def _cache_spec(cell: Cell):
    from testbed.envs.labelling import DopeSlamLabellingEnv

    try:
        env = DopeSlamLabellingEnv(scenario=str(cell.scenario), seeds=[int(cell.seed)], **_env_kwargs(cell))
    except (TypeError, ValueError) as e:
        raise MatrixError(f"cell {cell.label()}: {e}") from None
    return env, env.spec_for(0)


def cell_config(cell: Cell):
    """The cell's fully resolved :class:`testbed.settings.RunConfig` (raises :class:`MatrixError`)."""
    from stack.config import ConfigError, apply_sets
    from testbed.settings import RunConfig

    if cell_job(cell) != "run":
        raise MatrixError(f"cell {cell.label()}: a {cell_job(cell)} cell has no run config")
    sets = {"run.scenario": str(cell.scenario), "run.seed": int(cell.seed)}
    for k, v in cell.options.items():
        if k != "job":
            sets[SHORT_KEYS.get(k, k)] = v
    try:
        return apply_sets(RunConfig(), sets, source=lambda k: f"cell option {k!r}")
    except ConfigError as e:
        raise MatrixError(str(e)) from None


def _scenario_path(name) -> Path:
    from sim.scenario import ScenarioError, resolve_path

    try:
        p = resolve_path(name)
    except ScenarioError as e:
        raise MatrixError(str(e)) from None
    if not p.is_file():
        raise MatrixError(f"scenario {name!r}: no such file or bundled scenario")
    return p


def cell_key(cell: Cell) -> str:
    """16 hex digits, the same for the same inputs on any machine, changed by any input: the scenario
    file's content (and what it extends), the seed, the resolved config, the weights and thresholds
    files' content and the package version."""
    from stack.dope_fpr import default_thresholds_path, default_weights
    from testbed.provenance import file_sha256, package_version, scenario_sha256

    if cell_job(cell) == "perception-cache":  # the cache's own key names every input it depends on
        from testbed.envs.perception_cache import cache_dir

        env, spec = _cache_spec(cell)
        where = str(cache_dir(env.cache_dir).resolve())
        payload = {"job": "perception-cache", "spec": spec.stem(), "cache": where, "version": package_version()}
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]
    config = cell_config(cell)
    d = config.detector
    weights = d.weights or default_weights(d.input)
    thresholds = getattr(d, "thresholds", None) or default_thresholds_path(d.input)
    dump = config.model_dump(mode="json")
    dump["run"]["scenario"] = None  # the content counts, not the name it was given by
    payload = {"scenario": scenario_sha256(_scenario_path(cell.scenario)), "seed": int(cell.seed), "config": dump,
               "weights": file_sha256(weights), "thresholds": file_sha256(thresholds),
               "version": package_version()}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------ one cell

def execute(cell: Cell, out_dir: Path) -> dict:
    """Run one cell's episode into ``out_dir`` (as ``dopeslam run`` does); its report. A
    ``perception-cache`` cell builds (or finds) its episode's cache and writes a small report naming it."""
    from stack.interfaces import load_detector, resolve_policy
    from testbed.run import run_episode

    if cell_job(cell) == "perception-cache":
        from testbed.io import write_json

        t0 = time.perf_counter()
        env, spec = _cache_spec(cell)
        env.replay_for(0)
        env.close()
        report = {"job": "perception-cache", "scenario": str(cell.scenario), "seed": int(cell.seed),
                  "cache_stem": spec.stem(), "wall_seconds": time.perf_counter() - t0}
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        write_json(Path(out_dir) / "report.json", report)
        return report

    config = cell_config(cell)
    policy = resolve_policy(config.store.policy)
    detector = load_detector(config.components.detector) if config.components.detector else None
    r = config.run
    return run_episode(r.scenario, str(out_dir), r.seed, r.light, policy=policy, duration=r.duration,
                       detector=detector, config=config, odometry=config.components.odometry)


def finished_report(cell_dir: Path) -> dict | None:
    """A cell folder's report when the cell finished (report.json is written last), else None."""
    p = Path(cell_dir) / "report.json"
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return None


# cells side by side (--jobs over 1, a Ray task per core) already fill the cores: each keeps KISS-ICP
# in its own process, runs one detector process and renders its camera in its own process
# (docs/speed.md), unless the user set them
SIDE_BY_SIDE_DEFAULTS = {"DOPESLAM_ODOMETRY_PROCESS": "0", "DOPESLAM_DETECTOR_PROCESS": "1",
                         "DOPESLAM_RENDER_WORKER": "0"}


def _side_by_side_env() -> dict:
    return {k: os.environ.get(k, v) for k, v in SIDE_BY_SIDE_DEFAULTS.items()}


def _worker_env(jobs: int = 1) -> dict:
    """A cell process's environment: torch single-threaded; with ``jobs`` over 1,
    :data:`SIDE_BY_SIDE_DEFAULTS` where the user set nothing."""
    env = dict(os.environ)
    env.setdefault("DOPESLAM_TORCH_THREADS", "1")
    env.setdefault("OMP_NUM_THREADS", "1")
    if jobs > 1:
        env.update(_side_by_side_env())
    return env


WORKER = "import sys, testbed.matrix as m; sys.exit(m.worker_main(sys.argv[1:]))"


def worker_main(argv: list[str]) -> int:
    """A process backend's worker: ``CELL_JSON OUT_DIR RESULT_FILE``. Writes ``{"status", "error"}``."""
    from testbed.io import write_json

    spec, out_dir, result = json.loads(argv[0]), Path(argv[1]), Path(argv[2])
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    cell = Cell(spec["scenario"], int(spec["seed"]), dict(spec["options"]))
    try:
        execute(cell, out_dir)
        write_json(result, {"status": "ok", "error": None})
    except Exception as exc:  # the driver records it as the cell's error
        write_json(result, {"status": "error", "error": f"{type(exc).__name__}: {exc}"})
        return 1
    return 0


def _run_in_process(cell: Cell, cell_dir: Path, jobs: int = 1) -> tuple[str, str | None]:
    """One try of ``cell`` in a fresh interpreter; (status, error)."""
    cell_dir.parent.mkdir(parents=True, exist_ok=True)
    fd, result = tempfile.mkstemp(dir=cell_dir.parent, prefix=f".{cell_dir.name}.", suffix=".result.json")
    os.close(fd)
    os.unlink(result)
    spec = json.dumps({"scenario": str(cell.scenario), "seed": int(cell.seed), "options": cell.options})
    try:
        proc = subprocess.run([sys.executable, "-c", WORKER, spec, str(cell_dir), result], env=_worker_env(jobs),
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            outcome = json.loads(Path(result).read_text())
        except (OSError, ValueError):
            tail = (proc.stderr or "").strip().splitlines()[-1:] or [""]
            return "error", f"worker exited with status {proc.returncode}: {tail[0][:300]}"
        if outcome["status"] == "ok" and finished_report(cell_dir) is None:
            return "error", "worker finished without a report.json"
        return outcome["status"], outcome["error"]
    finally:
        Path(result).unlink(missing_ok=True)


# ------------------------------------------------------------------------------------------- Ray

def _ray_cell(spec: dict, collect_files: bool) -> dict:
    """A Ray task: the cell in a temporary folder on its node; the report and, when asked, the folder."""
    os.environ.setdefault("DOPESLAM_TORCH_THREADS", "1")
    cell = Cell(spec["scenario"], int(spec["seed"]), dict(spec["options"]))
    with tempfile.TemporaryDirectory(prefix="dopeslam-cell-") as tmp:
        out = Path(tmp) / "cell"
        try:
            execute(cell, out)
        except Exception as exc:
            return {"status": "error", "error": f"{type(exc).__name__}: {exc}"}
        report = finished_report(out)
        archive = None
        if collect_files:
            buf = io.BytesIO()
            with tarfile.open(fileobj=buf, mode="w:gz") as tar:
                tar.add(out, arcname=".")
            archive = buf.getvalue()
        return {"status": "ok" if report is not None else "error", "report": report, "archive": archive,
                "error": None if report is not None else "no report.json written"}


def check_ray_address(ray_address: str | None, timeout_s: float = 5.0) -> None:
    """A cluster's address (``HOST:PORT``, ``ray://HOST:PORT``; ``auto`` and None pass) that something
    answers at within ``timeout_s``; else a MatrixError in one line. Without this, Ray retries a wrong
    address for minutes before it gives up."""
    if not ray_address or ray_address == "auto":
        return
    import socket

    host, sep, port = ray_address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise MatrixError(f"--ray-address {ray_address}: expected HOST:PORT (a head node's, e.g. 10.0.0.5:6379), "
                          "ray://HOST:PORT or auto")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        why = "no answer" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise MatrixError(f"--ray-address {ray_address}: no Ray cluster answers there ({why} within {timeout_s:g} s); "
                          "start one with `ray start --head` or check the address") from None


def _ray(ray_address: str | None):
    try:
        import ray
    except ImportError:
        raise MatrixError("--ray: Ray is not installed; install it with: pip install -e '.[ray]'") from None
    check_ray_address(ray_address)
    if not ray.is_initialized():
        env = {"env_vars": {"DOPESLAM_TORCH_THREADS": "1", "OMP_NUM_THREADS": "1", **_side_by_side_env()}}
        extra = {}
        if ray_address and ray_address.split(":")[0] in ("127.0.0.1", "localhost"):
            extra["_node_ip_address"] = "127.0.0.1"  # a cluster on this machine's loopback: join it there
        try:
            ray.init(address=ray_address, runtime_env=env, log_to_driver=False, include_dashboard=False,
                     logging_level=logging.WARNING, **extra)
        except ConnectionError as exc:  # something answered, but not a Ray cluster's head
            raise MatrixError(f"--ray-address {ray_address}: {str(exc).splitlines()[0]}") from None
    return ray


def _store_ray_result(res: dict, cell_dir: Path) -> None:
    from testbed.io import output_dir, write_json

    with output_dir(cell_dir) as tmp:
        if res.get("archive"):
            with tarfile.open(fileobj=io.BytesIO(res["archive"]), mode="r:gz") as tar:
                tar.extractall(tmp, filter="data")  # no links or paths out of the folder
        write_json(Path(tmp) / "report.json", res["report"])


# ------------------------------------------------------------------------------------------ driver

def prepare_shared(cells) -> None:
    """Build once, on the driver, what many cells would otherwise each build: the place-recognition
    vocabulary of cells with loop closure and no vocabulary of their own. It lands in the cache
    (``$DOPESLAM_CACHE``), which every cell on this machine reads; a cluster node without it builds the
    same tree from the same seeded inputs once, into its own cache."""
    runs = [c for c in cells if cell_job(c) == "run"]
    if any(c.loop_closure.enabled and not c.loop_closure.vocabulary for c in map(cell_config, runs)):
        from testbed.vocabulary import build_vocabulary

        build_vocabulary()


def run_cells(cells, out_dir, jobs: int = 1, ray: bool = False, ray_address: str | None = None,
              progress: bool = True, collect_files: bool = False,
              on_result: Callable[[int, dict], None] | None = None) -> list[dict]:
    """Run every cell not already finished under ``out_dir``; one result per cell, in ``cells``' order:
    ``{"cell", "key", "status" ("ok"|"error"), "error", "report", "out_dir", "tries", "resumed"}``.
    ``on_result(i, result)`` is called on the driver as each cell ends (rows saved as they come)."""
    out_dir = Path(out_dir)
    cells = list(cells)
    keys = [cell_key(c) for c in cells]  # resolves every cell's options before anything runs
    if jobs < 1:
        raise MatrixError(f"--jobs: expected at least 1, got {jobs}")
    results: list[dict | None] = [None] * len(cells)
    todo = []
    for i, (c, k) in enumerate(zip(cells, keys)):
        d = out_dir / "cells" / k
        rep = finished_report(d)
        if rep is not None:
            results[i] = {"cell": c, "key": k, "status": "ok", "error": None, "report": rep, "out_dir": str(d),
                          "tries": 0, "resumed": True}
            if on_result:
                on_result(i, results[i])
        else:
            todo.append(i)
    prepare_shared([cells[i] for i in todo])
    from testbed import progress as bars

    # a bar only where the command line's bars are on (a terminal, no -q), as for every long command
    bar = _progress(len(cells), len(cells) - len(todo), progress and bars.enabled())

    def done(i: int, status: str, error: str | None, tries: int) -> None:
        d = out_dir / "cells" / keys[i]
        results[i] = {"cell": cells[i], "key": keys[i], "status": status, "error": error,
                      "report": finished_report(d) if status == "ok" else None, "out_dir": str(d), "tries": tries,
                      "resumed": False}
        if status != "ok":
            log.warning("cell %s failed after %d tries: %s", cells[i].label(), tries, error)
        if on_result:
            on_result(i, results[i])
        bar.update(1)

    try:
        if ray or ray_address:
            _drive_ray(cells, keys, todo, out_dir, ray_address, collect_files, done)
        else:
            _drive_processes(cells, keys, todo, out_dir, jobs, done)
    finally:
        bar.close()
    return [r for r in results if r is not None]


def _drive_processes(cells, keys, todo, out_dir, jobs, done) -> None:
    def attempt(i):
        tries, status, error = 0, "error", None
        while tries <= RETRIES:
            tries += 1
            status, error = _run_in_process(cells[i], out_dir / "cells" / keys[i], jobs)
            if status == "ok":
                break
        return i, status, error, tries

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        pending = {pool.submit(attempt, i) for i in todo}
        try:
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in finished:
                    done(*f.result())
        except KeyboardInterrupt:
            for f in pending:
                f.cancel()
            raise


def _drive_ray(cells, keys, todo, out_dir, ray_address, collect_files, done) -> None:
    ray = _ray(ray_address)
    task = ray.remote(num_cpus=1, max_retries=RETRIES)(_ray_cell)  # max_retries: a worker that dies
    specs = {i: {"scenario": str(cells[i].scenario), "seed": int(cells[i].seed), "options": cells[i].options}
             for i in todo}
    refs = {task.remote(specs[i], collect_files): (i, 1) for i in todo}
    while refs:
        ready, _ = ray.wait(list(refs), num_returns=1)
        i, tries = refs.pop(ready[0])
        try:
            res = ray.get(ready[0])
        except Exception as exc:  # the task's worker died more often than max_retries allows
            res = {"status": "error", "error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:300]}"}
        if res["status"] != "ok" and tries <= RETRIES:
            refs[task.remote(specs[i], collect_files)] = (i, tries + 1)
            continue
        if res["status"] == "ok":
            _store_ray_result(res, out_dir / "cells" / keys[i])
        done(i, res["status"], res.get("error"), tries)


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress(total: int, initial: int, enabled: bool):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="cell", desc="cells", file=sys.stderr, smoothing=0.1,
                dynamic_ncols=True, mininterval=1.0)


def now() -> float:
    return time.perf_counter()
