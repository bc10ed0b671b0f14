"""Persistent object store: one entry per physical object in the map (paper section 3.6).

A map-frame observation of an object is associated with the nearest stored object of the
same class within a gate, or starts a new object with the next unique integer ID. The
object's label (pose) is recomputed from its observation history by a labelling policy;
policies are plain functions of a list of observations, so they work offline too.

An object's history is bounded: past ``history_limit`` observations (4096 by default, more than an
object collects in any scenario shipped here) its older half is thinned, every second observation
dropped and counted by the one kept before it (``Observation.weight``), so a robot that watches an
object for hours keeps a few hundred kilobytes per object and a fixed cost per observation, with
counts and labels close to those of the whole history (see ``thin_history``).

The store is saved as ``.xlsx`` (one row per object, editable by hand, as in the paper)
or ``.json`` (the same plus each object's observation history). Saves are atomic. Rows
marked ``edited`` in the file being replaced are kept unless ``overwrite=True``. A file
that does not parse raises ObjectStoreError naming the file, row and column; loading
never writes.
"""
from __future__ import annotations

import json
import math
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from stack.evidence import CANDIDATE, LABEL, EvidenceConfig, assess, detected_range
from stack.errors import ComponentError, DopeSlamError
from stack.io import atomic_path, write_json
from stack.messages import Detection
from stack.retire import RETIRED, revive
from stack.transforms import from_xyz_quat, to_xyz_quat

COLUMNS = ["id", "class", "x", "y", "z", "qx", "qy", "qz", "qw", "size_x", "size_y", "size_z",
           "first_seen", "last_seen", "observations", "score", "edited", "status", "reason", "views"]
# files written before candidates existed: all labels; before views were counted: none counted
OPTIONAL_COLUMNS = {"status": LABEL, "reason": "", "views": 0}
SHEET = "objects"
JSON_FORMAT = "dopeslam-object-store"
QUAT_NORM_TOLERANCE = 0.01  # hand-typed quaternions (0.707, 0, 0, 0.707) are accepted and normalised


class ObjectStoreError(DopeSlamError, ValueError):
    """A store file that cannot be read: says which file, row and column, and what was expected.

    ``row`` is the spreadsheet row number (header = 1) for .xlsx, the index in ``objects``
    for .json, None when the whole file is at fault.
    """

    def __init__(self, path, row: int | None, column: str | None, message: str):
        self.path, self.row, self.column = Path(path), row, column
        xlsx = self.path.suffix.lower() == ".xlsx"
        where = [str(self.path)]
        if row is not None:
            where.append(f"row {row}" if xlsx else f"objects[{row}]")
        if column is not None:
            where.append(f"{'column' if xlsx else 'field'} '{column}'")
        super().__init__(f"{', '.join(where)}: {message}")


@dataclass
class Observation:
    """One detection of an object, already carried into the map frame."""

    stamp: float
    cls: str
    xyz: np.ndarray  # (3,) map frame, metres
    quat_xyzw: np.ndarray  # (4,) orientation of the object frame in the map
    belief_sum: float = math.nan  # FPR's quantity: lower = more certain
    fpr_pass: bool = True
    range_m: float = math.nan  # camera-to-object distance when seen
    cam_xyz: np.ndarray | None = None  # (3,) camera position in the map when seen (the viewpoint)
    weight: int = 1  # how many observations this one stands for (more than 1 once a long history was thinned)

    @staticmethod
    def from_detection(det: Detection, T_map_obj: np.ndarray, T_map_cam: np.ndarray | None = None) -> "Observation":
        xyz, quat = to_xyz_quat(T_map_obj)
        cam = None if T_map_cam is None else np.array(T_map_cam[:3, 3], dtype=float)
        return Observation(det.stamp, det.cls, xyz, quat, float(det.belief_sum), bool(det.fpr_pass),
                           float(np.linalg.norm(det.T_cam_obj[:3, 3])), cam)

    def to_dict(self) -> dict:
        d = {"stamp": self.stamp, "cls": self.cls, "xyz": [float(v) for v in self.xyz],
             "quat_xyzw": [float(v) for v in self.quat_xyzw], "belief_sum": _nan_to_none(self.belief_sum),
             "fpr_pass": self.fpr_pass, "range_m": _nan_to_none(self.range_m)}
        if self.cam_xyz is not None:
            d["cam_xyz"] = [float(v) for v in self.cam_xyz]
        if self.weight != 1:
            d["weight"] = int(self.weight)
        return d

    @staticmethod
    def from_dict(d: Mapping) -> "Observation":
        xyz, quat = np.asarray(d["xyz"], dtype=float), np.asarray(d["quat_xyzw"], dtype=float)
        cam = None if d.get("cam_xyz") is None else np.asarray(d["cam_xyz"], dtype=float)
        if xyz.shape != (3,) or quat.shape != (4,) or (cam is not None and cam.shape != (3,)):
            raise ValueError("expected xyz of 3, quat_xyzw of 4 and cam_xyz (if given) of 3 numbers")
        weight = d.get("weight", 1)
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or weight != int(weight) or weight < 1:
            raise ValueError(f"expected a weight that is a whole number >= 1, got {weight!r}")
        return Observation(float(d["stamp"]), str(d["cls"]), xyz, quat, _none_to_nan(d.get("belief_sum")),
                           bool(d.get("fpr_pass", True)), _none_to_nan(d.get("range_m")), cam, int(weight))


# --- Labelling policies: observations (time order) -> label, or None when none qualifies ---------

@dataclass
class Label:
    xyz: np.ndarray
    quat_xyzw: np.ndarray
    score: float  # belief sum of what the label rests on (lower = more certain)


Policy = Callable[[Sequence[Observation]], "Label | None"]
POLICIES: dict[str, Policy] = {}


def register(name: str):
    def add(fn: Policy) -> Policy:
        POLICIES[name] = fn
        return fn
    return add


def get_policy(name: str) -> Policy:
    if name not in POLICIES:
        raise KeyError(f"unknown labelling policy {name!r}; expected one of {sorted(POLICIES)}")
    return POLICIES[name]


def label_of(observations: Sequence[Observation], policy: str = "robust-mean") -> Label | None:
    """The label ``policy`` gives ``observations``: None, or a :class:`Label` with a finite ``xyz`` (3,)
    and ``quat_xyzw`` (4,); anything else from a policy is a :class:`stack.errors.ComponentError`
    naming it."""
    label = get_policy(policy)(observations)
    if label is None:
        return None
    if not isinstance(label, Label):
        why = f"a {type(label).__name__}; expected None or stack.object_store.Label"
    else:
        why = _not_numbers(label.xyz, 3, "xyz") or _not_numbers(label.quat_xyzw, 4, "quat_xyzw")
    if why:
        raise ComponentError(f"policy {policy}: for {len(observations)} observation(s) of class "
                             f"{observations[0].cls if observations else '?'} it returned {why}")
    return label


def _not_numbers(value, size: int, name: str) -> str:
    """Why ``value`` is not ``size`` finite numbers ('' when it is)."""
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        array = None
    if array is None or array.shape != (size,) or not np.isfinite(array).all():
        return f"a Label whose {name} is {value!r}; expected {size} finite numbers"
    return ""


def _label(o: Observation) -> Label:
    return Label(np.array(o.xyz, dtype=float), np.array(o.quat_xyzw, dtype=float), o.belief_sum)


def _latest(obs: Sequence[Observation]) -> Observation | None:
    return max(reversed(obs), key=lambda o: o.stamp) if obs else None  # ties: the later in the list


def _passing(obs: Sequence[Observation]) -> list[Observation]:
    return [o for o in obs if o.fpr_pass]


@register("last")
def last(obs: Sequence[Observation]) -> Label | None:
    """The paper's: the last detection is the label, even if FPR rejected it."""
    o = _latest(obs)
    return None if o is None else _label(o)


@register("last-fpr")
def last_fpr(obs: Sequence[Observation]) -> Label | None:
    """The last detection that passed FPR (the paper's with FPR filtering what reaches the map)."""
    o = _latest(_passing(obs))
    return None if o is None else _label(o)


@register("best-score")
def best_score(obs: Sequence[Observation]) -> Label | None:
    """The FPR-passing detection with the lowest belief sum (the most certain one)."""
    ok = _passing(obs)
    if not ok:
        return None
    return _label(min(ok, key=lambda o: o.belief_sum if not math.isnan(o.belief_sum) else math.inf))


@register("closest-fpr")
def closest_fpr(obs: Sequence[Observation]) -> Label | None:
    """The FPR-passing detection taken nearest the camera (PnP depth error grows with range)."""
    ok = _passing(obs)
    if not ok:
        return None
    return _label(min(ok, key=lambda o: o.range_m if not math.isnan(o.range_m) else math.inf))


@register("robust-mean")
def robust_mean(obs: Sequence[Observation], k: float = 3.0, floor_m: float = 0.02) -> Label | None:
    """Mean of the FPR-passing detections left after rejecting outliers around their median.

    A detection is an outlier when it is further from the coordinate-wise median than
    k robust sigmas (1.4826 x the median distance), and never within ``floor_m``.
    Observations that stand for several (``weight``, in a thinned history) count that many times:
    weighted medians, means and rotation mean.
    """
    ok = _passing(obs)
    if not ok:
        return None
    P = np.array([o.xyz for o in ok], dtype=float)
    if any(o.weight != 1 for o in ok):
        return _robust_mean_weighted(ok, P, k, floor_m)
    r = np.linalg.norm(P - np.median(P, axis=0), axis=1)
    inlier = r <= max(k * 1.4826 * np.median(r), floor_m)
    quat = Rotation.from_quat(np.array([o.quat_xyzw for o in ok])[inlier]).mean().as_quat()
    beliefs = np.array([o.belief_sum for o in ok])[inlier]
    score = float(np.mean(beliefs[~np.isnan(beliefs)])) if np.any(~np.isnan(beliefs)) else math.nan
    return Label(P[inlier].mean(axis=0), quat, score)


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The median of ``values`` with each repeated ``weights`` times (whole numbers): for unit weights,
    ``np.median`` (the mean of the two middle values when their number is even)."""
    order = np.argsort(values, kind="stable")
    v, c = np.asarray(values, dtype=float)[order], np.cumsum(np.asarray(weights)[order])
    total = c[-1]
    lo = v[np.searchsorted(c, (total - 1) // 2, side="right")]  # the values at the middle position(s)
    hi = v[np.searchsorted(c, total // 2, side="right")]
    return float(0.5 * (lo + hi))


def _robust_mean_weighted(ok: Sequence[Observation], P: np.ndarray, k: float, floor_m: float) -> Label:
    w = np.array([o.weight for o in ok], dtype=np.int64)
    med = np.array([weighted_median(P[:, i], w) for i in range(3)])
    r = np.linalg.norm(P - med, axis=1)
    inlier = r <= max(k * 1.4826 * weighted_median(r, w), floor_m)
    wi = w[inlier].astype(float)
    quat = Rotation.from_quat(np.array([o.quat_xyzw for o in ok])[inlier]).mean(weights=wi).as_quat()
    beliefs = np.array([o.belief_sum for o in ok])[inlier]
    known = ~np.isnan(beliefs)
    score = float(np.average(beliefs[known], weights=wi[known])) if np.any(known) else math.nan
    return Label(np.average(P[inlier], axis=0, weights=wi), quat, score)


HISTORY_LIMIT = 4096  # observations an object keeps before its older half is thinned (``thin_history``)


def thin_history(history: list[Observation], keep_newest: int, keep_older: int) -> list[Observation]:
    """``history`` (time order) with its observations before the newest ``keep_newest`` thinned to about
    ``keep_older``: the FPR-passing ones and the rejected ones are each cut, in time order, into runs
    of equal total ``weight`` W (the smallest power of two that leaves at most ``keep_older``), and
    each run is kept as its first observation, standing for the whole run (its ``weight``). So sums
    of weights (the evidence's counts) stay exact, and the kept observations sample the past evenly
    (medians and means over them, weighted, follow those over the whole history).

    Kept as they are: the newest ``keep_newest`` (``last``, ``last-fpr`` and what the label follows
    now), the first observation and the first passing one (the time span), and the passing ones with
    the lowest belief sum and the shortest range (``best-score``, ``closest-fpr``)."""
    cut = max(0, len(history) - max(0, int(keep_newest)))
    older, newest = history[:cut], history[cut:]
    passing = [o for o in history if o.fpr_pass]
    pinned = {id(history[0])} if history else set()
    if passing:
        pinned.add(id(passing[0]))
        pinned.add(id(min(passing, key=lambda o: o.belief_sum if not math.isnan(o.belief_sum) else math.inf)))
        pinned.add(id(min(passing, key=lambda o: o.range_m if not math.isnan(o.range_m) else math.inf)))
    groups = [[i for i, o in enumerate(older) if o.fpr_pass == flag and id(o) not in pinned] for flag in (True, False)]
    totals = [sum(older[i].weight for i in g) for g in groups]
    run_weight = 1
    while sum(-(-t // run_weight) for t in totals) > max(1, int(keep_older)):
        run_weight *= 2
    kept: dict[int, Observation] = {i: o for i, o in enumerate(older) if id(o) in pinned}
    for g in groups:
        first, weight = None, 0
        for i in g:
            if first is None:
                first = i
            weight += older[i].weight
            if weight >= run_weight:
                kept[first] = _with_weight(older[first], weight)
                first, weight = None, 0
        if first is not None:
            kept[first] = _with_weight(older[first], weight)
    return [kept[i] for i in sorted(kept)] + list(newest)


def _with_weight(o: Observation, weight: int) -> Observation:
    if weight == o.weight:
        return o
    return Observation(o.stamp, o.cls, o.xyz, o.quat_xyzw, o.belief_sum, o.fpr_pass, o.range_m, o.cam_xyz, int(weight))


# --- The store ------------------------------------------------------------------------------------

@dataclass
class MapObject:
    id: int
    cls: str
    xyz: np.ndarray  # label position (cuboid centroid), map frame
    quat_xyzw: np.ndarray
    size: np.ndarray  # cuboid x y z, metres
    first_seen: float
    last_seen: float
    observations: int = 0
    score: float = math.nan
    edited: bool = False  # set by a person: the stack no longer moves it and saves keep it
    status: str = LABEL  # "label": published; "candidate": kept, not (yet) a label; "retired": its place seen empty
    reason: str = ""  # why a candidate is not a label
    history: list[Observation] = field(default_factory=list)
    past: list[Observation] = field(default_factory=list)  # observations before it was retired and seen again
    sightings: list[Observation] = field(default_factory=list)  # seen while retired, not yet enough to revive it
    revive_after: int = 3  # sightings of a retired object that bring it back (RetireConfig.revive_sightings)
    views: int = 0  # detected images that showed its place (``stack.evidence.count_views``)
    view_range_m: float = math.nan  # the furthest FPR-passing observation's range (nan: not yet known)

    @property
    def is_label(self) -> bool:
        return self.status == LABEL

    @property
    def T_map_obj(self) -> np.ndarray:
        return from_xyz_quat(self.xyz, self.quat_xyzw)

    def row(self) -> dict:
        (x, y, z), (qx, qy, qz, qw), (sx, sy, sz) = self.xyz, self.quat_xyzw, self.size
        values = [self.id, self.cls, x, y, z, qx, qy, qz, qw, sx, sy, sz,
                  self.first_seen, self.last_seen, self.observations, self.score, self.edited, self.status,
                  self.reason, self.views]
        return {c: (v.item() if isinstance(v, np.generic) else v) for c, v in zip(COLUMNS, values)}


class ObjectStore:
    """Objects by ID; ``add`` associates an observation and relabels the object.

    ``dims``: cuboid size per class (also the set of known classes). ``gate_m``: the
    furthest an observation may be from an object's label to be that object
    (math.inf = one object per class, as in the paper's one-object runs).
    ``evidence``: what an object needs to be published as a label (``stack.evidence``);
    None publishes every object. ``floor``: the floor plane in the map (n, d), from the
    odometry, for the evidence's floor check. ``publish()`` sets every object's status.
    ``history_limit``: the observations an object keeps before its older half is thinned
    (``thin_history``; at least 2).
    """

    def __init__(self, dims: Mapping[str, Sequence[float]] | None = None, gate_m: float = 0.5,
                 policy: str = "robust-mean", evidence: EvidenceConfig | None = EvidenceConfig(),
                 history_limit: int = HISTORY_LIMIT):
        get_policy(policy)
        if int(history_limit) < 2:
            raise ValueError(f"history_limit must be at least 2, got {history_limit}")
        self.history_limit = int(history_limit)
        self.dims = {c: np.asarray(v, dtype=float) for c, v in (dims or {}).items()}
        self.gate_m = float(gate_m)
        self.policy = policy
        self.evidence = evidence
        self.floor: tuple[np.ndarray, float] | None = None
        self.objects: dict[int, MapObject] = {}

    def publish(self) -> dict:
        """Decide each object's status (label or candidate) from its evidence; returns the evidence by id.

        Objects edited by hand keep the status a person gave them, and objects loaded without their
        observation history (from .xlsx) keep the status they were saved with.
        """
        judged = [o for o in self if o.history and not o.edited and o.status != RETIRED]
        if self.evidence is None:
            for obj in judged:
                obj.status, obj.reason = LABEL, ""
            return {}
        verdicts = assess(judged, self.evidence, self.floor)
        for obj in judged:
            obj.status, obj.reason, _ = verdicts[obj.id]
        return {i: v[2] for i, v in verdicts.items()}

    def labels(self) -> list[MapObject]:
        """The published labels (call ``publish()`` first for an up-to-date verdict)."""
        return [o for o in self if o.is_label]

    def candidates(self) -> list[MapObject]:
        return [o for o in self if not o.is_label]

    def __len__(self) -> int:
        return len(self.objects)

    def __iter__(self):
        return iter(sorted(self.objects.values(), key=lambda o: o.id))

    def next_id(self) -> int:
        return max(self.objects, default=0) + 1

    def associate(self, cls: str, xyz, exclude_edited: bool = False) -> MapObject | None:
        """The nearest object of class ``cls`` within the gate, or None."""
        best, best_d = None, self.gate_m
        for obj in self.objects.values():
            if obj.cls != cls or (exclude_edited and obj.edited):
                continue
            d = float(np.linalg.norm(np.asarray(xyz, dtype=float) - obj.xyz))
            if d <= best_d:
                best, best_d = obj, d
        return best

    def add(self, obs: Observation) -> MapObject | None:
        """Record an observation; returns its object, or None when it labels nothing new.

        An observation that matches no object starts one only if the policy would label it
        on its own (an FPR-rejected detection does not create an object under `last-fpr`).
        """
        obj = self.associate(obs.cls, obs.xyz)
        if obj is None:
            if label_of([obs], self.policy) is None:
                return None
            if obs.cls not in self.dims:
                raise ComponentError(f"a detection of class {obs.cls!r} at t={float(obs.stamp):.3f} s: no cuboid "
                                     f"size for that class; the detector's classes must be among the map's "
                                     f"{sorted(self.dims)}")
            obj = MapObject(self.next_id(), obs.cls, np.array(obs.xyz, dtype=float),
                            np.array(obs.quat_xyzw, dtype=float), self.dims[obs.cls].copy(), obs.stamp, obs.stamp)
            self.objects[obj.id] = obj
        if obj.status == RETIRED and not obj.edited:
            if not obs.fpr_pass:  # a detection FPR rejected is no sighting: the object stays retired
                return obj
            obj.sightings.append(obs)  # one stray detection near an emptied place does not bring it back
            if len(obj.sightings) < obj.revive_after:
                return obj
            pending, obj.sightings = obj.sightings[:-1], []
            revive(obj)  # seen again: it comes back, labelled from what is seen from now on
            for o in pending:
                self._record(obj, o)
        self._record(obj, obs)
        return obj

    def _record(self, obj: MapObject, obs: Observation) -> None:
        obj.history.append(obs)
        if len(obj.history) > self.history_limit:
            obj.history = thin_history(obj.history, self.history_limit // 2, self.history_limit // 4)
        obj.observations += obs.weight
        if obs.fpr_pass and math.isfinite(obs.range_m):  # (a loaded object's history counts too)
            obj.view_range_m = max(detected_range(obj), float(obs.range_m))
        obj.first_seen, obj.last_seen = min(obj.first_seen, obs.stamp), max(obj.last_seen, obs.stamp)
        if not obj.edited:
            label = label_of(obj.history, self.policy)
            if label is not None:
                obj.xyz, obj.quat_xyzw, obj.score = label.xyz, label.quat_xyzw, label.score

    # --- persistence ---

    def save(self, path, overwrite: bool = False) -> None:
        """Write the store to ``path`` (.xlsx or .json), atomically.

        Unless ``overwrite``, rows marked edited in the file being replaced are kept as
        they are, and the store adopts them first (see ``keep_edited``); a replaced file
        that does not parse raises ObjectStoreError and is left as it is.
        """
        path = Path(path)
        writer = _writer(path)
        if path.exists() and not overwrite:
            self.keep_edited(read_objects(path, classes=set(self.dims) or None))
        writer(path, list(self), self.floor)

    def keep_edited(self, objects: Sequence[MapObject]) -> None:
        """Take hand-edited objects in as they are, replacing what the store has for them.

        An edited object replaces the stored object with its ID and class, or else the nearest
        unedited stored object of its class within the gate (the same object under another ID).
        A different stored object holding its ID is given a new ID.
        """
        for e in (o for o in objects if o.edited):
            same = self.objects.get(e.id)
            if same is None or same.cls != e.cls:
                same = self.associate(e.cls, e.xyz, exclude_edited=True)
            if same is not None:
                del self.objects[same.id]
                e.history = e.history or same.history
            if e.id in self.objects:
                other = self.objects.pop(e.id)
                other.id = max(self.next_id(), e.id + 1)
                self.objects[other.id] = other
            self.objects[e.id] = e

    @classmethod
    def load(cls, path, dims: Mapping[str, Sequence[float]] | None = None, gate_m: float = 0.5,
             policy: str = "robust-mean", evidence: EvidenceConfig | None = EvidenceConfig()) -> "ObjectStore":
        store = cls(dims, gate_m, policy, evidence)
        for obj in read_objects(path, classes=set(store.dims) or None):
            store.objects[obj.id] = obj
        if Path(path).suffix.lower() == ".json":
            store.floor = _read_floor(Path(path))
        return store


# --- Files ----------------------------------------------------------------------------------------

def read_objects(path, classes: set[str] | None = None) -> list[MapObject]:
    """Objects from a .xlsx or .json store file; ObjectStoreError if anything is malformed."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".xlsx":
        return _read_xlsx(path, classes)
    if suffix == ".json":
        return _read_json(path, classes)
    raise ObjectStoreError(path, None, None, f"unknown store format {suffix!r}; expected .xlsx or .json")


def _writer(path: Path):
    suffix = path.suffix.lower()
    if suffix == ".xlsx":
        return _write_xlsx
    if suffix == ".json":
        return _write_json
    raise ValueError(f"{path}: unknown store format {suffix!r}; expected .xlsx or .json")


def _xlsx_cell(value):
    """A row's value as pandas' ``to_excel`` hands it to openpyxl: missing (None, NaN) as an empty
    string, infinities as the strings ``inf`` and ``-inf``, everything else as it is."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return value


def _write_xlsx(path: Path, objects: Sequence[MapObject], floor=None) -> None:
    """One sheet, a header row of ``COLUMNS`` and a row per object, written by openpyxl itself: the
    same workbook parts, byte for byte, as pandas' ``DataFrame.to_excel`` made of it (only the creation
    time differs), without pandas' 0.4 s of import."""
    import openpyxl  # here, not at the top: the processes that only detect never load it

    book = openpyxl.Workbook()
    sheet = book.active
    sheet.title = SHEET
    sheet.append(COLUMNS)
    for o in objects:
        row = o.row()
        sheet.append([_xlsx_cell(row[c]) for c in COLUMNS])
    with atomic_path(path) as tmp, open(tmp, "wb") as f:  # our handle: closed even if openpyxl fails midway
        book.save(f)


def _write_json(path: Path, objects: Sequence[MapObject], floor=None) -> None:
    doc = {"format": JSON_FORMAT, "version": 1,
           "floor": None if floor is None else {"normal": [float(v) for v in floor[0]], "d_m": float(floor[1])},
           "objects": [
        {**{c: _nan_to_none(v) for c, v in o.row().items()}, "history": [h.to_dict() for h in o.history]}
        for o in objects]}
    write_json(path, doc, indent=1)


def _read_xlsx(path: Path, classes: set[str] | None) -> list[MapObject]:
    import openpyxl
    from openpyxl.utils.exceptions import InvalidFileException

    try:
        wb = openpyxl.load_workbook(path, read_only=True, data_only=True)
    except (OSError, zipfile.BadZipFile, InvalidFileException, KeyError, ValueError) as e:
        raise ObjectStoreError(path, None, None, f"not a readable .xlsx workbook ({e})") from e
    try:
        ws = wb[SHEET] if SHEET in wb.sheetnames else wb.worksheets[0]
        rows = ws.iter_rows(values_only=True)
        header = [str(h).strip() if h is not None else "" for h in next(rows, ())]
        for c in COLUMNS:
            if c not in header and c not in OPTIONAL_COLUMNS:
                raise ObjectStoreError(path, 1, c, f"missing column; the header must hold {COLUMNS}")
            if header.count(c) > 1:
                raise ObjectStoreError(path, 1, c, "column appears more than once")
        where = {c: header.index(c) for c in COLUMNS if c in header}
        records = []
        for number, cells in enumerate(rows, start=2):
            cells = list(cells) + [None] * (len(header) - len(cells))
            if all(v is None or (isinstance(v, str) and not v.strip()) for v in cells):
                continue  # a blank line is no object
            records.append((number, {c: cells[i] for c, i in where.items()}))
    finally:
        wb.close()
    return _objects_from_records(path, records, classes)


def _read_floor(path: Path) -> tuple[np.ndarray, float] | None:
    """The floor plane a .json store was saved with (n, d in map), or None."""
    floor = json.loads(path.read_text()).get("floor")
    if floor is None:
        return None
    try:
        n, d = np.asarray(floor["normal"], dtype=float), float(floor["d_m"])
    except (KeyError, TypeError, ValueError) as e:
        raise ObjectStoreError(path, None, "floor", f"expected {{'normal': [x, y, z], 'd_m': d}} ({e})") from e
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not math.isfinite(d) or abs(np.linalg.norm(n) - 1) > 1e-3:
        raise ObjectStoreError(path, None, "floor", f"expected a unit normal of 3 numbers and a finite d_m, got {floor}")
    return n, d


def _read_json(path: Path, classes: set[str] | None) -> list[MapObject]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ObjectStoreError(path, None, None, f"not readable JSON ({e})") from e
    if not isinstance(doc, dict) or doc.get("format") != JSON_FORMAT or not isinstance(doc.get("objects"), list):
        raise ObjectStoreError(path, None, None, f"expected an object {{'format': '{JSON_FORMAT}', 'objects': [...]}}")
    records = []
    for i, item in enumerate(doc["objects"]):
        if not isinstance(item, dict):
            raise ObjectStoreError(path, i, None, "expected an object with the store's columns")
        for c in COLUMNS:
            if c not in item and c not in OPTIONAL_COLUMNS:
                raise ObjectStoreError(path, i, c, "missing field")
        records.append((i, item))
    objects = _objects_from_records(path, records, classes)
    for (i, item), obj in zip(records, objects):
        for k, h in enumerate(item.get("history") or []):
            try:
                obj.history.append(Observation.from_dict(h))
            except (KeyError, TypeError, ValueError) as e:
                raise ObjectStoreError(path, i, f"history[{k}]", f"malformed observation ({e})") from e
    return objects


def _objects_from_records(path: Path, records, classes: set[str] | None) -> list[MapObject]:
    objects, first_row_of_id = [], {}
    for row, values in records:
        obj = _parse_row(path, row, values, classes)
        if obj.id in first_row_of_id:
            raise ObjectStoreError(path, row, "id", f"id {obj.id} is used twice (first at row {first_row_of_id[obj.id]})")
        first_row_of_id[obj.id] = row
        objects.append(obj)
    return objects


def _parse_row(path: Path, row: int, v: Mapping, classes: set[str] | None) -> MapObject:
    def number(c: str, allow_empty: bool = False) -> float:
        x = v[c]
        if _empty(x):
            if allow_empty:
                return math.nan
            raise ObjectStoreError(path, row, c, "empty cell; expected a number")
        if isinstance(x, bool):
            raise ObjectStoreError(path, row, c, f"expected a number, got {x!r}")
        try:
            f = float(x)
        except (TypeError, ValueError):
            raise ObjectStoreError(path, row, c, f"expected a number, got {x!r}") from None
        if not math.isfinite(f) and not allow_empty:
            raise ObjectStoreError(path, row, c, f"expected a finite number, got {x!r}")
        return f

    def integer(c: str) -> int:
        f = number(c)
        if f != int(f) or f < 0:
            raise ObjectStoreError(path, row, c, f"expected a whole number >= 0, got {v[c]!r}")
        return int(f)

    cls = v["class"]
    if not isinstance(cls, str) or not cls.strip():
        raise ObjectStoreError(path, row, "class", f"expected a class name, got {cls!r}")
    cls = cls.strip()
    if classes is not None and cls not in classes:
        raise ObjectStoreError(path, row, "class", f"unknown class {cls!r}; expected one of {sorted(classes)}")

    quat = np.array([number(c) for c in ("qx", "qy", "qz", "qw")])
    norm = float(np.linalg.norm(quat))
    if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
        raise ObjectStoreError(path, row, "qx..qw", f"quaternion {quat.tolist()} has norm {norm:.4g}; expected a unit quaternion")
    size = np.array([number(c) for c in ("size_x", "size_y", "size_z")])
    for c, s in zip(("size_x", "size_y", "size_z"), size):
        if s <= 0:
            raise ObjectStoreError(path, row, c, f"expected a size > 0 m, got {s}")
    first_seen, last_seen = number("first_seen"), number("last_seen")
    if last_seen < first_seen:
        raise ObjectStoreError(path, row, "last_seen", f"last_seen {last_seen} is before first_seen {first_seen}")
    status = v.get("status")
    status = LABEL if _empty(status) else str(status).strip().lower()
    if status not in (LABEL, CANDIDATE, RETIRED):
        raise ObjectStoreError(path, row, "status", f"expected {LABEL!r}, {CANDIDATE!r} or {RETIRED!r}, "
                               f"got {v.get('status')!r}")
    reason = v.get("reason")
    views = 0 if _empty(v.get("views")) else integer("views")
    return MapObject(
        id=integer("id"), cls=cls, xyz=np.array([number(c) for c in ("x", "y", "z")]), quat_xyzw=quat / norm,
        size=size, first_seen=first_seen, last_seen=last_seen, observations=integer("observations"),
        score=number("score", allow_empty=True), edited=_flag(path, row, v["edited"]), status=status,
        reason="" if _empty(reason) else str(reason), views=views)


def _flag(path: Path, row: int, x) -> bool:
    if _empty(x):
        return False
    if isinstance(x, bool):
        return x
    if isinstance(x, (int, float)) and x in (0, 1):
        return bool(x)
    if isinstance(x, str) and x.strip().lower() in ("true", "yes", "y", "1", "false", "no", "n", "0"):
        return x.strip().lower() in ("true", "yes", "y", "1")
    raise ObjectStoreError(path, row, "edited", f"expected TRUE or FALSE, got {x!r}")


def _empty(x) -> bool:
    return x is None or (isinstance(x, str) and not x.strip()) or (isinstance(x, float) and math.isnan(x))


def _nan_to_none(x):
    return None if isinstance(x, float) and math.isnan(x) else x


def _none_to_nan(x) -> float:
    return math.nan if x is None else float(x)
