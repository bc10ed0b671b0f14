"""Scoring of the whole map a user receives against the simulator's ground truth.

Every published label is matched one to one to a true object of its class (an assignment that
first makes as many matches within the threshold as possible, then the nearest ones). A label
matched within ``FALSE_LABEL_M`` of its object is correct; every other label is false:

- **misplaced**: matched to an object of its class, but further than the threshold;
- **phantom**: matched to nothing (a second label of one object, a wrong class on a real
  object, or a label where there is no object at all).

Map precision is correct / labels in the map, map recall correct / objects. Candidates (objects
the stack kept but did not publish) are counted, never scored as labels.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from stack.errors import DopeSlamError
from stack.transforms import transform_points

FALSE_LABEL_M = 0.25  # a label further than this from its object's truth is a false label


def assign(label_cls: list[str], label_xyz: np.ndarray, truth_cls: list[str], truth_xyz: np.ndarray,
           threshold_m: float = FALSE_LABEL_M) -> dict[int, tuple[int, float]]:
    """label index -> (object index, distance) for the one-to-one matching of labels to objects of
    their class; the most matches within ``threshold_m`` first, then the least total distance."""
    label_xyz = np.asarray(label_xyz, dtype=float).reshape(-1, 3)
    truth_xyz = np.asarray(truth_xyz, dtype=float).reshape(-1, 3)
    if not len(label_xyz) or not len(truth_xyz):
        return {}
    d = np.linalg.norm(label_xyz[:, None] - truth_xyz[None], axis=2)
    same = np.asarray(label_cls)[:, None] == np.asarray(truth_cls)[None]
    big = 1e6  # a match beyond the threshold costs more than any number of matches within it
    cost = np.where(same, np.where(d <= threshold_m, d, big + d), 1e12)
    rows, cols = linear_sum_assignment(cost)
    return {int(r): (int(c), float(d[r, c])) for r, c in zip(rows, cols) if same[r, c]}


def score_map(published, objects, T_world_map: np.ndarray, n_candidates: int = 0,
              threshold_m: float = FALSE_LABEL_M) -> tuple[list[dict], list[dict], dict]:
    """(one row per true object, one row per published label, the summary).

    ``published``: the labels in the map (``id``, ``cls``, ``xyz`` in map, ``observations``), e.g.
    ``ObjectStore.labels()``; ``objects``: the true objects (``name``, ``cls``, ``T_world_obj``);
    ``n_candidates``: how many objects the stack kept without publishing them (reported only).
    """
    published = list(published)
    xyz = transform_points(T_world_map, np.array([m.xyz for m in published]).reshape(-1, 3))
    truth = np.array([o.T_world_obj[:3, 3] for o in objects]).reshape(-1, 3)
    match = assign([m.cls for m in published], xyz, [o.cls for o in objects], truth, threshold_m)
    by_object = {k: (i, dist) for i, (k, dist) in match.items()}

    map_rows = []
    for i, m in enumerate(published):
        row = {"id": m.id, "class": m.cls, "label_xyz": [float(v) for v in xyz[i]], "observations": m.observations}
        if i in match:
            k, dist = match[i]
            row.update({"object": objects[k].name, "error_m": dist,
                        "verdict": "correct" if dist <= threshold_m else "misplaced"})
        else:
            row.update({"object": None, "error_m": None, "nearest_object_m": _nearest(xyz[i], truth),
                        "verdict": "phantom"})
        map_rows.append(row)

    rows = []
    for k, obj in enumerate(objects):
        row = {"object": obj.name, "class": obj.cls, "truth_xyz": [float(v) for v in truth[k]]}
        if k not in by_object:
            row.update({"id": None, "label_xyz": None, "error_m": None, "false_label": None, "missing": True})
        else:
            i, dist = by_object[k]
            m, d = published[i], xyz[i] - truth[k]
            row.update({"id": m.id, "label_xyz": [float(v) for v in xyz[i]], "error_m": dist,
                        "dx_m": float(d[0]), "dy_m": float(d[1]), "dz_m": float(d[2]),
                        "false_label": bool(dist > threshold_m), "missing": dist > threshold_m,
                        "observations": m.observations})
        rows.append(row)
    return rows, map_rows, summarize(rows, map_rows, n_candidates=n_candidates, threshold_m=threshold_m)


def summarize(rows: list[dict], map_rows: list[dict], n_candidates: int = 0,
              threshold_m: float = FALSE_LABEL_M) -> dict:
    verdicts = [r["verdict"] for r in map_rows]
    correct, misplaced, phantom = (verdicts.count(v) for v in ("correct", "misplaced", "phantom"))
    errs = [r["error_m"] for r in rows if r["error_m"] is not None]
    n_obj, n_map = len(rows), len(map_rows)
    return {"objects": n_obj, "labels_in_map": n_map, "correct_labels": correct,
            "false_labels": misplaced + phantom, "misplaced": misplaced, "phantom": phantom,
            "map_precision": correct / n_map if n_map else None,
            "map_recall": correct / n_obj if n_obj else None,
            "labelled": correct, "missing": n_obj - correct,
            "mean_error_m": float(np.mean(errs)) if errs else None,
            "candidates": n_candidates, "false_label_threshold_m": threshold_m}


def summary_line(s: dict) -> str:
    """The map's score in one line, as every command prints it."""
    prec = "-" if s["map_precision"] is None else f"{100 * s['map_precision']:.0f} %"
    err = "-" if s["mean_error_m"] is None else f"{100 * s['mean_error_m']:.1f} cm"
    return (f"map: {s['labels_in_map']} labels, {s['correct_labels']} correct, {s['false_labels']} false "
            f"({s['misplaced']} misplaced, {s['phantom']} phantom); precision {prec}, "
            f"{s['correct_labels']}/{s['objects']} objects labelled; mean error {err}; "
            f"{s['candidates']} candidates not published")


def _nearest(p: np.ndarray, truth: np.ndarray) -> float | None:
    return float(np.min(np.linalg.norm(truth - p, axis=1))) if len(truth) else None


class RunDirError(DopeSlamError, ValueError):
    """A run folder that cannot be scored again (names the file and what is wrong)."""


def rescore_run(run_dir, evidence=None) -> dict:
    """Publish a saved run's object store again (``labels.json``: every object with its observations)
    under ``evidence`` (a ``stack.evidence.EvidenceConfig``; None = the defaults) and score the map
    against the run's ground truth (``report.json``'s objects, ``groundtruth_tum.txt``'s first pose
    for ``T_world_map``). Returns the summary, with ``map_labels`` and ``run``."""
    import json
    from pathlib import Path
    from types import SimpleNamespace

    from stack.evidence import EvidenceConfig, carry_views
    from stack.metrics import read_tum
    from stack.object_store import ObjectStore, ObjectStoreError

    run_dir = Path(run_dir)
    report_path, labels_path, gt_path = (run_dir / n for n in ("report.json", "labels.json", "groundtruth_tum.txt"))
    for p in (report_path, labels_path, gt_path):
        if not p.is_file():
            raise RunDirError(f"{p}: missing; expected a folder written by `dopeslam run`")
    try:
        report = json.loads(report_path.read_text())
        truth_rows = report["labels"]
        objects = [SimpleNamespace(name=str(r["object"]), cls=str(r["class"]),
                                   T_world_obj=_translation(r["truth_xyz"])) for r in truth_rows]
    except (ValueError, KeyError, TypeError) as e:
        raise RunDirError(f"{report_path}: field 'labels': expected rows with object, class and truth_xyz ({e})") from e
    try:
        saved = ObjectStore.load(labels_path)
    except ObjectStoreError as e:
        raise RunDirError(str(e)) from e
    floor = saved.floor
    if floor is None and report.get("map_floor"):
        floor = (np.asarray(report["map_floor"]["normal"], dtype=float), float(report["map_floor"]["d_m"]))
    store = ObjectStore(dims={o.cls: o.size for o in saved}, policy=report.get("policy", "robust-mean"),
                        evidence=evidence or EvidenceConfig())
    for obs in sorted((h for o in saved for h in o.history), key=lambda h: h.stamp):
        store.add(obs)
    carry_views(saved, store)  # the images that showed each place, as the run counted them
    store.floor = floor
    store.publish()
    _, T_world_base = read_tum(gt_path)
    rows, map_rows, summary = score_map(store.labels(), objects, T_world_base[0], len(store.candidates()))
    return {**summary, "map_labels": map_rows, "run": str(run_dir), "scenario": report.get("scenario"),
            "seed": report.get("seed"), "input": report.get("input")}


def _translation(xyz) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = np.asarray(xyz, dtype=float).reshape(3)
    return T
