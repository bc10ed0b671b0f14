"""Golden outputs of the stack's four drivers, recorded and compared bit for bit.

    python tests/golden_record.py record DIR     # dopeslam run, record + replay, one perception cache
    python tests/golden_record.py compare A B    # every recorded file of A against B; exit 1 on a difference

``record`` writes, under DIR:

- ``run/``: ``dopeslam run --duration 20 --seed 0`` (labels.json, estimate_tum.txt, report.json, ...)
- ``bag.bag`` and ``replay/``: ``dopeslam record --duration 10 --seed 0`` then ``dopeslam replay --sequential``
- ``cache/``: the gym env's perception cache of the default scenario, seed 0, 10 s, real DOPE

``compare`` checks labels.json and the TUM trajectories byte for byte, the cache's arrays exactly
(``np.array_equal``, NaN equal to NaN), and the parts of report.json that the stack computes
(detection counts, label errors, trajectory scores), ignoring timings. Run both with one torch
thread (``DOPESLAM_TORCH_THREADS=1``, set here) so DOPE's sums come out in the same order.

The commands run the code of the tree this file is in, from any working directory: to record an
older commit, check it out beside this one (``git worktree add OLD COMMIT``) and run
``python OLD/tests/golden_record.py record DIR`` with this environment's Python.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

os.environ.setdefault("DOPESLAM_TORCH_THREADS", "1")

RUN = ["run", "--duration", "20", "--seed", "0"]
RECORD = ["record", "--duration", "10", "--seed", "0"]
CACHE_SEED, CACHE_DURATION = 0, 10.0
TEXT_FILES = ["run/labels.json", "run/estimate_tum.txt", "run/groundtruth_tum.txt",
              "replay/labels.json", "replay/estimate_tum.txt", "replay/groundtruth_tum.txt"]
REPORT_KEYS = ["detection", "labels", "labels_summary", "candidates", "odometry", "wheel_odometry", "map_floor"]
TIMING_KEYS = {"fps", "seconds_total", "odometry_hz"}


ROOT = Path(__file__).resolve().parents[1]  # the tree whose code is recorded
if str(ROOT) not in sys.path[:1]:
    sys.path.insert(0, str(ROOT))  # ahead of an installed copy of another tree


def dopeslam(*args: str) -> None:
    cmd = [sys.executable, "-m", "testbed.cli", *args]
    print("+ dopeslam", " ".join(args), flush=True)
    # from ROOT, with ROOT first on the path (``package_env``, as the commands give their own child
    # processes): ``-m`` puts the working directory ahead of everything
    from sim.child import package_env  # ROOT's own, found first (above)

    subprocess.run(cmd, check=True, cwd=ROOT, env=package_env())


def build_cache(folder: Path) -> Path:
    from sim.scenario import DEFAULT_SCENARIO
    from testbed.envs import perception_cache as pc

    factory, det_id, kept = pc.dope_factory("rgb", 6)
    spec = pc.make_spec(DEFAULT_SCENARIO, CACHE_SEED, CACHE_DURATION, None, "rgb", kept, det_id)
    got = pc.build(spec, factory, folder, progress=False)
    return pc.paths_for(got.spec, folder)[1]


def record(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    dopeslam(*RUN, "--out", str(out / "run"))
    dopeslam(*RECORD, "--bag", str(out / "bag.bag"), "--force")
    dopeslam("replay", str(out / "bag.bag"), "--out", str(out / "replay"), "--sequential")
    npz = build_cache(out / "cache")
    print(f"recorded {out}: run/, bag.bag, replay/, {npz.relative_to(out)}")


def _strip_timing(x):
    """Timings left out; NaN read as None (one JSON writer writes NaN, another null), so NaN == NaN."""
    if isinstance(x, float) and x != x:
        return None
    if isinstance(x, dict):
        return {k: _strip_timing(v) for k, v in x.items() if k not in TIMING_KEYS}
    if isinstance(x, list):
        return [_strip_timing(v) for v in x]
    return x


def _cache_arrays(folder: Path) -> tuple[Path, dict]:
    npz = sorted(p for p in folder.glob("*.npz") if not p.name.endswith(".thumbs.npz"))
    if len(npz) != 1:
        raise SystemExit(f"{folder}: expected one cache .npz, found {len(npz)}")
    with np.load(npz[0], allow_pickle=False) as z:
        return npz[0], {k: z[k] for k in z.files}


def compare(a: Path, b: Path) -> list[str]:
    """The differences between two recordings, one line each (empty: identical)."""
    diffs = []
    for rel in TEXT_FILES:
        pa, pb = a / rel, b / rel
        if not pa.exists() or not pb.exists():
            diffs.append(f"{rel}: missing in {a if not pa.exists() else b}")
        elif pa.read_bytes() != pb.read_bytes():
            diffs.append(f"{rel}: differs")
    for rel in ("run/report.json", "replay/report.json"):
        ra, rb = json.loads((a / rel).read_text()), json.loads((b / rel).read_text())
        for key in REPORT_KEYS:
            if key in ra or key in rb:
                va, vb = _strip_timing(ra.get(key)), _strip_timing(rb.get(key))
                if va != vb:
                    diffs.append(f"{rel}: {key!r} differs")
    (na, xa), (nb, xb) = _cache_arrays(a / "cache"), _cache_arrays(b / "cache")
    if na.name != nb.name:
        diffs.append(f"cache: file name (spec) differs: {na.name} vs {nb.name}")
    skip = {"frame_detect_s"}  # wall-clock seconds
    for k in sorted(set(xa) | set(xb)):
        if k in skip:
            continue
        if k not in xa or k not in xb:
            diffs.append(f"cache: array {k!r} only in {a if k in xa else b}")
        elif xa[k].shape != xb[k].shape or not np.array_equal(xa[k], xb[k], equal_nan=xa[k].dtype.kind == "f"):
            diffs.append(f"cache: array {k!r} differs ({xa[k].shape} vs {xb[k].shape})")
    meta_a = json.loads(na.with_suffix(".json").read_text())
    meta_b = json.loads(nb.with_suffix(".json").read_text())
    for key in ("frames", "detections", "dropped_no_pose", "objects"):
        if meta_a.get(key) != meta_b.get(key):
            diffs.append(f"cache: meta {key!r} differs: {meta_a.get(key)} vs {meta_b.get(key)}")
    return diffs


def main(argv: list[str]) -> int:
    if len(argv) == 2 and argv[0] == "record":
        record(Path(argv[1]).resolve())  # the commands run from this tree's folder
        return 0
    if len(argv) == 3 and argv[0] == "compare":
        diffs = compare(Path(argv[1]), Path(argv[2]))
        for d in diffs:
            print(d)
        print("identical" if not diffs else f"{len(diffs)} difference(s)")
        return 1 if diffs else 0
    print(__doc__.strip().splitlines()[2:4], file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
