"""The labelling state shared by the labelling envs: object slots, their labels, and the map's cost.

A *slot* is one candidate object in the map. Each detection is associated with the nearest
active slot of its class whose anchor (the mean of the detections associated so far) is within
the gate, or opens the next free slot; when none is free, the unlabelled slot seen longest ago is
recycled (a candidate the policy never labelled: typically a false detection), and only when every
slot holds a label or a detection of this frame is the detection dropped. Association does not
depend on the actions until slots run out, so every policy sees the same slots for the same
episode as long as there are enough of them. At most one detection per slot per frame: when
two fall into one slot, the one that passed FPR with the lower belief sum is kept.

The policy then decides per slot what the current detection does to that slot's label:

- ``IGNORE`` (0): nothing;
- ``REPLACE`` (1): the label becomes this detection (its evidence is this detection alone);
- ``FUSE`` (2): the detection joins the label's evidence, and the label is the robust mean of the
  evidence: the mean of the positions within k robust sigmas of their median (as the store's
  ``robust-mean`` policy; ``stack.object_store.robust_mean``);
- ``WITHDRAW`` (3): the slot's label is taken off the map (the slot is a candidate again, as the
  stack keeps an object it does not publish). The label's evidence is kept, and a current
  detection that passed FPR joins it, so a later ``FUSE`` publishes the label with all of it.
  Unlike the other actions it applies to every slot in use, with or without a detection this frame.

Each slot also carries its evidence as ``stack.evidence`` defines it (``EvidenceConfig``: what an
object needs before the stack publishes it), from the slot's detections, whatever the labels: the
FPR-passing detections within the camera's range (``max_range_m``), the time between the first and
last of them, the largest angle between their viewing rays to the slot's anchor (as it was at the
latest of them), the anchor's
height above the floor plane the odometry fitted (and the lowest corner of the class's cuboid
there, oriented as the slot's latest detection: the stack's floor check), and the class vote: the
share of the FPR-passing detections of the slots within ``vote_radius_m`` of the anchor that are
of the slot's class, and its lead: the slot's FPR-passing detections over those plus the strongest
other class's there (the stack publishes only the best-supported class at a place: a lead of at
least 0.5).

The map's *cost* scores the labels against the truth the way ``testbed.scoring.score_map`` does:
per class, a one-to-one assignment of labels to true objects (``linear_sum_assignment``; the most
matches within 0.25 m first, then the least total distance). A matched label costs its distance
(plus ``false_label_penalty`` when it is further than 0.25 m: a misplaced label), an object with
no label costs ``missing_cost_m``, and a label matched to no object (a phantom: a second label of
one object, or a label where there is no object of its class) costs ``extra_label_penalty``.
The reward of a step is the decrease of the cost, so an episode's return is the initial cost
(every object missing) less the final one.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from stack.evidence import EvidenceConfig
from testbed.scoring import FALSE_LABEL_M

IGNORE, REPLACE, FUSE, WITHDRAW = 0, 1, 2, 3
N_ACTIONS = 4
ROBUST_K = 3.0  # as stack.object_store.robust_mean
ROBUST_FLOOR_M = 0.02

POSITION_LIMIT_M = 1000.0
VALUE_LIMIT = 1.0e6
_BEYOND = 1.0e6  # an assignment cost: a match beyond the threshold costs more than any within it (as scoring.assign)


@dataclass(frozen=True)
class RewardConfig:
    missing_cost_m: float = 0.5  # an object without a label costs as much as a label this far off
    false_label_penalty: float = 0.5  # added to a matched label's error when it is over 0.25 m
    extra_label_penalty: float = 0.25  # a label that no true object claims (a phantom label)
    stage_cost_per_s: float = 0.05  # reward lost per second of DOPE time (with stage choice)


EVIDENCE_FEATURES = ["ev_fpr_detections", "ev_span_s", "ev_view_angle_deg", "ev_anchor_height_m",
                     "ev_floor_clearance_m", "ev_vote_share", "ev_vote_lead"]


def slot_features(n_classes: int) -> list[str]:
    """Names of the columns of the observation's ``slots`` array."""
    return (["present", "active"] + [f"class_{i}" for i in range(n_classes)]
            + ["det_x", "det_y", "det_z", "det_belief", "det_fpr", "det_range_m", "det_stages"]
            + ["has_label", "label_x", "label_y", "label_z", "label_log_evidence", "label_belief",
               "det_label_dist_m", "log_detections"]
            + EVIDENCE_FEATURES)


def floor_half_extents(quat_xyzw: np.ndarray, cls: np.ndarray, dims_by_class: np.ndarray,
                       floor: tuple[np.ndarray, float] | None) -> np.ndarray:
    """Per detection: half the extent of its class's cuboid, in its orientation, along the floor's
    normal (the anchor's height less this is the lowest corner's, as ``stack.evidence``); 0 without a floor."""
    quat_xyzw = np.asarray(quat_xyzw, dtype=float).reshape(-1, 4)
    if floor is None or not len(quat_xyzw):
        return np.zeros(len(quat_xyzw))
    n = np.asarray(floor[0], dtype=float)
    R = Rotation.from_quat(quat_xyzw).as_matrix()  # (M, 3, 3)
    return 0.5 * np.einsum("mi,mi->m", np.abs(np.einsum("mji,j->mi", R, n)), dims_by_class[np.asarray(cls, dtype=int)])


class SlotMap:
    """Slots, labels, evidence and cost for one episode.

    Detections come as a dict of arrays (``perception_cache.DET_FIELDS`` plus ``err``, the distance
    to the nearest true object of the class, for the oracles; ``stamp``, the frame's time; ``half``,
    ``floor_half_extents``) and the same columns as Python lists under ``<name>_list``
    (``with_lists``): association runs per detection in plain Python, which for a dozen slots is
    faster than numpy's per-call overhead. ``floor``: the floor plane (n, d) in map the odometry
    fitted (n.x + d is a height above it), or None; ``evidence``: the stack's publishing rule, whose
    range limit and vote radius the slots' evidence columns use.
    """

    def __init__(self, n_slots: int, n_classes: int, truth_cls: np.ndarray, truth_xyz: np.ndarray,
                 gate_m: float = 0.5, reward: RewardConfig = RewardConfig(),
                 floor: tuple[np.ndarray, float] | None = None, evidence: EvidenceConfig | None = None):
        self.N, self.C = int(n_slots), int(n_classes)
        self.truth_cls = np.asarray(truth_cls, dtype=np.int64)
        self.truth_xyz = np.asarray(truth_xyz, dtype=np.float64).reshape(-1, 3)
        self.gate2 = float(gate_m) ** 2
        self.reward = reward
        self.evidence = evidence or EvidenceConfig()
        self.floor = None if floor is None else (np.asarray(floor[0], dtype=float).reshape(3), float(floor[1]))
        N = self.N
        self.cls = np.full(N, -1, dtype=np.int64)
        self.class_slots: dict[int, list[int]] = {}
        self.n_free = N
        self.anchor_sum = [[0.0, 0.0, 0.0] for _ in range(N)]
        self.n_dets = [0] * N
        self.has = np.zeros(N, dtype=bool)
        self._labelled: set[int] = set()  # slots with a label (mirror of ``has``)
        self._labelled_by_class: dict[int, list[int]] = {}
        self.label = np.zeros((N, 3))
        self.label_belief = np.zeros(N)
        self.label_err = np.full(N, np.nan)
        self._ev = np.zeros((N, 64, 3))
        self._ev_belief = np.zeros((N, 64))
        self.ev_n = np.zeros(N, dtype=np.int64)  # the label's evidence (kept while withdrawn)
        # the slot's evidence as the stack counts it: FPR-passing detections within range
        self.fpr_n = [0] * N
        self.fpr_first = [0.0] * N
        self.fpr_last = [0.0] * N
        self._cams = np.zeros((N, 64, 3))
        self.n_cams = [0] * N
        self.half = [0.0] * N  # floor half-extent of the slot's latest detection
        self.angle = [0.0] * N  # largest angle between viewing rays (deg), as of the latest viewpoint
        self.cur = np.full(N, -1, dtype=np.int64)  # index of the current detection per slot
        self._present: list[int] = []
        self.dets: dict | None = None
        self.stage = 0
        self.dropped = 0  # detections with no free slot
        self.recycled = 0  # unlabelled slots given to a new candidate
        self.withdrawn = 0  # labels taken off the map
        self.frame_no = 0
        self.last_seen = [-1] * N
        self.duplicates = 0  # second detections of a slot in one frame
        self._truth = self.truth_xyz.tolist()
        self._truth_cls = self.truth_cls.tolist()
        self._truth_by_class: dict[int, list[int]] = {}
        for k, c in enumerate(self._truth_cls):
            self._truth_by_class.setdefault(c, []).append(k)
        self._D = [[math.inf] * N for _ in range(len(self._truth_cls))]
        self._class_cost = {c: len(ks) * reward.missing_cost_m for c, ks in self._truth_by_class.items()}
        self.cost = self._cost()
        names = slot_features(self.C)
        self._col = {n: k for k, n in enumerate(names)}
        self._det0 = self._col["det_x"]
        self._lab0 = self._col["has_label"]
        self._ev0 = self._col[EVIDENCE_FEATURES[0]]
        self._obs = np.zeros((N, len(names)), dtype=np.float32)
        self._minus_ones = np.full(N, -1.0)

    # --- association -------------------------------------------------------------------------------
    def observe(self, dets: dict, lo: int, hi: int, stage: int) -> None:
        """Make detections lo..hi-1 of ``dets`` the current ones, associating each with a slot."""
        self.dets, self.stage = dets, stage
        self.frame_no += 1
        can_recycle = True  # until a search finds nothing (it cannot find more later in this frame)
        cur, o = self.cur, self._obs
        for j in self._present:
            cur[j] = -1
            o[j, 0] = 0.0
            o[j, self._det0:self._det0 + 7] = 0.0
            o[j, self._lab0 + 6] = 0.0
        self._present = []
        if hi <= lo:
            return
        cls, xyz, fpr, belief = dets["cls_list"], dets["xyz_list"], dets["fpr_list"], dets["belief_list"]
        gate2 = self.gate2
        for i in range(lo, hi):
            c = cls[i]
            x, y, z = xyz[i]
            j, best = -1, gate2
            for k in self.class_slots.get(c, ()):
                sx, sy, sz = self.anchor_sum[k]
                n = self.n_dets[k]
                d2 = (sx / n - x) ** 2 + (sy / n - y) ** 2 + (sz / n - z) ** 2
                if d2 <= best:
                    j, best = k, d2
            if j < 0:
                if self.n_free:
                    j = self.N - self.n_free
                    self.n_free -= 1
                else:
                    j = self._recycle() if can_recycle else -1
                    if j < 0:
                        can_recycle = False
                        self.dropped += 1
                        continue
                self.cls[j] = c
                self.class_slots.setdefault(c, []).append(j)
                o[j, 1] = 1.0
                o[j, 2 + c] = 1.0
            if cur[j] >= 0:
                self.duplicates += 1
                k = cur[j]
                if (fpr[k], -belief[k]) >= (fpr[i], -belief[i]):
                    continue
            else:
                self._present.append(j)
            cur[j] = i
            self.last_seen[j] = self.frame_no
            a = self.anchor_sum[j]
            a[0] += x
            a[1] += y
            a[2] += z
            self.n_dets[j] += 1
            o[j, self._lab0 + 7] = math.log1p(self.n_dets[j])
        b = self._det0
        st = stage / 6.0
        rng, stamps, cams, halves = dets["range_list"], dets.get("stamp_list"), dets.get("cam_list"), dets.get("half_list")
        max_range = self.evidence.max_range_m
        for j in self._present:
            i = cur[j]
            x, y, z = xyz[i]
            o[j, 0] = 1.0
            o[j, b:b + 7] = (_bounded(x), _bounded(y), _bounded(z), _bounded(belief[i]), float(fpr[i]),
                             _bounded(rng[i]), st)
            if self.has[j]:
                lx, ly, lz = self.label[j]
                o[j, self._lab0 + 6] = _bounded(math.sqrt((x - lx) ** 2 + (y - ly) ** 2 + (z - lz) ** 2))
            if halves is not None:
                self.half[j] = halves[i]
            if fpr[i] and not rng[i] > max_range:  # as stack.evidence: NaN range counts
                t = stamps[i] if stamps is not None else float(self.frame_no)
                if self.fpr_n[j] == 0:
                    self.fpr_first[j] = t
                self.fpr_last[j] = t
                self.fpr_n[j] += 1
                if cams is not None:
                    self._add_cam(j, cams[i])
                    self._view_angle(j)
            self._evidence_columns(j)
        self._vote_columns()

    def _add_cam(self, j: int, cam) -> None:
        n = self.n_cams[j]
        if n == self._cams.shape[1]:
            self._cams = np.concatenate([self._cams, np.zeros_like(self._cams)], axis=1)
        self._cams[j, n] = cam
        self.n_cams[j] = n + 1

    def anchor(self, j: int) -> tuple[float, float, float]:
        n = self.n_dets[j]
        sx, sy, sz = self.anchor_sum[j]
        return (sx / n, sy / n, sz / n) if n else (0.0, 0.0, 0.0)

    def _view_angle(self, j: int) -> None:
        """Slot j's largest angle between viewing rays to its anchor (recomputed when a viewpoint joins)."""
        ax, ay, az = self.anchor(j)
        angle = 0.0
        n = self.n_cams[j]
        if n >= 2:
            rays = np.array((ax, ay, az)) - self._cams[j, :n]
            norms = np.sqrt(np.einsum("ij,ij->i", rays, rays))
            if norms.min() > 1e-9:
                rays /= norms[:, None]
            else:
                rays = rays[norms > 1e-9] / norms[norms > 1e-9, None]
            if len(rays) >= 2:  # as stack.evidence.view_angle_deg (the sum points as the mean does)
                a = rays[np.argmin(rays @ rays.sum(axis=0))]
                bb = rays[np.argmin(rays @ a)]
                angle = math.degrees(math.acos(min(max(float(a @ bb), -1.0), 1.0)))
        self.angle[j] = angle if angle == angle else 0.0  # NaN (a non-finite position): no angle

    def _evidence_columns(self, j: int) -> None:
        """Slot j's evidence columns (but the vote share) from its detections so far."""
        e, o = self._ev0, self._obs
        ax, ay, az = self.anchor(j)
        height = clearance = 0.0
        if self.floor is not None:
            fn, fd = self.floor
            height = float(fn[0] * ax + fn[1] * ay + fn[2] * az + fd)
            clearance = height - self.half[j]
        span = self.fpr_last[j] - self.fpr_first[j] if self.fpr_n[j] else 0.0
        o[j, e:e + 5] = (self.fpr_n[j], _bounded(span), self.angle[j], _bounded(height), _bounded(clearance))

    def _vote_columns(self) -> None:
        """Every slot's class-vote share: of the FPR-passing detections of the slots whose anchors lie
        within ``vote_radius_m`` of its anchor (itself included), the fraction of its class (0 with none)."""
        used = [j for j in range(self.N) if self.n_dets[j]]
        if not used:
            return
        A = np.array([self.anchor(j) for j in used])
        w = np.array([self.fpr_n[j] for j in used], dtype=float)
        c = self.cls[used]
        diff = A[:, None] - A[None]
        near = np.einsum("ijk,ijk->ij", diff, diff) < self.evidence.vote_radius_m ** 2
        total = near @ w
        same = (near & (c[:, None] == c[None])) @ w
        share = np.divide(same, total, out=np.zeros_like(total), where=total > 0)
        # the strongest other class at the place: the stack's vote goes to the most supported class
        by_class = np.stack([(near & (c[None] == k)) @ w for k in range(self.C)], axis=1)  # (U, C)
        by_class[np.arange(len(used)), c] = 0.0
        rival = by_class.max(axis=1)
        lead = np.divide(w, w + rival, out=np.zeros_like(w), where=(w + rival) > 0)
        self._obs[used, self._ev0 + 5] = share
        self._obs[used, self._ev0 + 6] = lead

    def _recycle(self) -> int:
        """Free the unlabelled slot seen longest ago (not one of this frame's); -1 if there is none."""
        j, oldest = -1, self.frame_no
        cur = self.cur.tolist()
        for k in range(self.N):
            if k not in self._labelled and cur[k] < 0 and self.last_seen[k] < oldest:
                j, oldest = k, self.last_seen[k]
        if j < 0:
            return -1
        self.class_slots[int(self.cls[j])].remove(j)
        self.cls[j] = -1
        self.anchor_sum[j] = [0.0, 0.0, 0.0]
        self.n_dets[j] = 0
        self.ev_n[j] = 0
        self.fpr_n[j] = 0
        self.n_cams[j] = 0
        self.half[j] = 0.0
        self.angle[j] = 0.0
        self._obs[j] = 0.0
        self.recycled += 1
        return j

    # --- actions ---------------------------------------------------------------------------------
    def act(self, labels: np.ndarray) -> float:
        """Apply per-slot actions (``IGNORE``, ``REPLACE``, ``FUSE`` to the current detections,
        ``WITHDRAW`` to any slot); returns the decrease of the cost."""
        labels = labels.tolist() if hasattr(labels, "tolist") else list(labels)
        changed = []
        if WITHDRAW in labels:
            for j in sorted(self._labelled):
                if labels[j] == WITHDRAW:
                    self._withdraw(j)
                    changed.append(j)
        if not self._present and not changed:
            return 0.0
        dets = self.dets
        published = []
        for j in self._present:
            a = labels[j]
            if a == IGNORE:
                continue
            i = int(self.cur[j])
            if a == WITHDRAW:
                if not dets["fpr_list"][i]:
                    continue
            elif a == REPLACE:
                self.ev_n[j] = 0
            n = int(self.ev_n[j])
            if n == self._ev.shape[1]:
                self._ev = np.concatenate([self._ev, np.zeros_like(self._ev)], axis=1)
                self._ev_belief = np.concatenate([self._ev_belief, np.zeros_like(self._ev_belief)], axis=1)
            p = dets["xyz_list"][i]
            self._ev[j, n] = p
            self._ev_belief[j, n] = dets["belief_list"][i]
            self.ev_n[j] = n + 1
            if n == 0:
                self.label[j] = p
                self.label_belief[j] = dets["belief_list"][i]
            else:
                self.label[j], self.label_belief[j] = _robust_mean(self._ev[j, :n + 1], self._ev_belief[j, :n + 1])
            if a == WITHDRAW:
                self._obs[j, self._lab0 + 4] = math.log1p(self.ev_n[j])
                continue
            if j not in self._labelled:
                self.has[j] = True
                self._labelled.add(j)
                bisect.insort(self._labelled_by_class.setdefault(int(self.cls[j]), []), j)  # slot order, as final_score
            published.append(j)
        if not changed and not published:
            return 0.0
        o, L = self._obs, self._lab0
        for j in published:
            lx, ly, lz = self.label[j]
            o[j, L:L + 6] = (1.0, _bounded(lx), _bounded(ly), _bounded(lz), math.log1p(self.ev_n[j]),
                             _bounded(self.label_belief[j]))
            if self.cur[j] >= 0:
                x, y, z = dets["xyz_list"][int(self.cur[j])]
                o[j, L + 6] = _bounded(math.sqrt((x - lx) ** 2 + (y - ly) ** 2 + (z - lz) ** 2))
        before = self.cost
        self.cost = self._cost(changed + published)
        return before - self.cost

    def _withdraw(self, j: int) -> None:
        """Take slot j's label off the map; its evidence stays (a later FUSE continues from it)."""
        self.has[j] = False
        self._labelled.discard(j)
        self._labelled_by_class[int(self.cls[j])].remove(j)
        L = self._lab0
        self._obs[j, L:L + 4] = 0.0
        self._obs[j, L + 5:L + 7] = 0.0
        self.withdrawn += 1

    # --- cost / score ------------------------------------------------------------------------------
    def _cost(self, changed=()) -> float:
        """The map's cost with the labels matched to objects as ``testbed.scoring.score_map`` does
        (per class a one-to-one assignment: the most matches within 0.25 m, then the least distance).
        ``changed``: slots whose label moved, appeared or was withdrawn since the last call; only their
        column of the distance table and their classes' assignments are recomputed."""
        D, truth = self._D, self._truth
        classes = set()
        for j in changed:
            c = int(self.cls[j])
            classes.add(c)
            if not self.has[j]:
                continue
            lx, ly, lz = self.label[j].tolist()
            best = math.inf
            for k in self._truth_by_class.get(c, ()):
                tx, ty, tz = truth[k]
                e = math.sqrt((tx - lx) ** 2 + (ty - ly) ** 2 + (tz - lz) ** 2)
                D[k][j] = e
                best = min(best, e)
            self.label_err[j] = best
        for c in classes:
            self._class_cost[c] = self._class_cost_of(c)
        return float(sum(self._class_cost.values()))

    def _class_cost_of(self, c: int) -> float:
        r = self.reward
        objs = self._truth_by_class.get(c, [])
        labs = self._labelled_by_class.get(c, [])
        if not labs or not objs:
            return r.missing_cost_m * len(objs) + r.extra_label_penalty * len(labs)
        D = self._D
        if len(objs) == 1 and len(labs) == 1:
            dists = [D[objs[0]][labs[0]]]
        else:
            d = np.array([[D[k][j] for k in objs] for j in labs])
            rows, cols = linear_sum_assignment(np.where(d <= FALSE_LABEL_M, d, _BEYOND + d))
            dists = d[rows, cols].tolist()
        m = len(dists)
        cost = sum(e + (r.false_label_penalty if e > FALSE_LABEL_M else 0.0) for e in dists)
        return cost + r.missing_cost_m * (len(objs) - m) + r.extra_label_penalty * (len(labs) - m)

    def errors_to_truth(self, xyz: np.ndarray, cls: np.ndarray) -> np.ndarray:
        """Distance of each position to the nearest true object of its class (inf if none)."""
        xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
        if not len(self.truth_cls) or not len(xyz):
            return np.full(len(xyz), np.inf)
        D = np.linalg.norm(xyz[:, None, :] - self.truth_xyz[None], axis=2)
        D[np.asarray(cls)[:, None] != self.truth_cls[None]] = np.inf
        return D.min(axis=1)

    # --- observation ---------------------------------------------------------------------------------
    def slots_obs(self) -> np.ndarray:
        return self._obs.copy()

    def oracle_info(self) -> tuple[np.ndarray, np.ndarray]:
        """(distance to truth of each slot's current detection, of each slot's label); -1 where there is
        none (not NaN: gymnasium's determinism check compares infos with ==). A distance is to the
        nearest true object of the class, inf when the scene has none of that class."""
        det_err = self._minus_ones.copy()
        if self._present:
            errs = self.dets["err_list"]
            for j in self._present:
                det_err[j] = errs[self.cur[j]]
        return det_err, np.where(self.has, self.label_err, -1.0)


def with_lists(dets: dict) -> dict:
    """Add ``<name>_list`` Python-list copies of the per-detection columns ``SlotMap`` reads."""
    out = dict(dets)
    for k in ("cls", "xyz", "fpr", "belief", "range", "err", "stamp", "cam", "half"):
        if k in dets:
            out[f"{k}_list"] = np.asarray(dets[k]).tolist()
    return out


def _bounded(v: float) -> float:
    if v != v:  # NaN
        return 0.0
    return min(max(float(v), -VALUE_LIMIT), VALUE_LIMIT)


def _median(a: np.ndarray) -> np.ndarray:
    """Median along axis 0 (as np.median, without its overhead)."""
    n = len(a)
    h = n // 2
    if n % 2:
        return np.partition(a, h, axis=0)[h]
    q = np.partition(a, (h - 1, h), axis=0)
    return 0.5 * (q[h - 1] + q[h])


def _robust_mean(P: np.ndarray, beliefs: np.ndarray) -> tuple[np.ndarray, float]:
    """``stack.object_store.robust_mean`` on positions: the mean of those within k robust sigmas of the
    median (never nearer than the floor); with the mean belief sum of the kept ones (NaNs skipped)."""
    n = len(P)
    if n <= 2:  # both points are equally far from their midpoint: both are kept
        w = np.ones(n)
    else:
        diff = P - _median(P)
        r = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        w = (r <= max(ROBUST_K * 1.4826 * float(_median(r)), ROBUST_FLOOR_M)).astype(np.float64)
    cnt = w.sum()
    belief = float(w @ beliefs)
    if belief != belief:  # some belief sums are NaN: average the finite ones
        ok = np.isfinite(beliefs) & (w > 0)
        belief = float(beliefs[ok].mean()) if ok.any() else float("nan")
    else:
        belief /= cnt
    return (w @ P) / cnt, belief
