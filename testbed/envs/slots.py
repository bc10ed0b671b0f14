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
  ``robust-mean`` policy; ``stack.object_store.robust_mean``).

The map's *cost* scores the labels against the truth the way ``testbed.run.score_labels`` does:
each true object, in order, takes the nearest unused label of its class; a matched label costs
its distance (plus ``false_label_penalty`` when it is further than 0.25 m: a false label), an
object with no label costs ``missing_cost_m``, and a label matched to no object costs
``extra_label_penalty``. The reward of a step is the decrease of the cost, so an episode's
return is the initial cost (every object missing) less the final one.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from testbed.run import FALSE_LABEL_M

IGNORE, REPLACE, FUSE = 0, 1, 2
ROBUST_K = 3.0  # as stack.object_store.robust_mean
ROBUST_FLOOR_M = 0.02

POSITION_LIMIT_M = 1000.0
VALUE_LIMIT = 1.0e6


@dataclass(frozen=True)
class RewardConfig:
    missing_cost_m: float = 0.5  # an object without a label costs as much as a label this far off
    false_label_penalty: float = 0.5  # added to a matched label's error when it is over 0.25 m
    extra_label_penalty: float = 0.25  # a label that no true object claims (a phantom object)
    stage_cost_per_s: float = 0.05  # reward lost per second of DOPE time (with stage choice)


def slot_features(n_classes: int) -> list[str]:
    """Names of the columns of the observation's ``slots`` array."""
    return (["present", "active"] + [f"class_{i}" for i in range(n_classes)]
            + ["det_x", "det_y", "det_z", "det_belief", "det_fpr", "det_range_m", "det_stages"]
            + ["has_label", "label_x", "label_y", "label_z", "label_log_evidence", "label_belief",
               "det_label_dist_m", "log_detections"])


class SlotMap:
    """Slots, labels and cost for one episode.

    Detections come as a dict of arrays (``perception_cache.DET_FIELDS`` plus ``err``, the distance
    to the nearest true object of the class, for the oracles) and the same columns as Python lists
    under ``<name>_list`` (``with_lists``): association runs per detection in plain Python, which
    for a dozen slots is faster than numpy's per-call overhead.
    """

    def __init__(self, n_slots: int, n_classes: int, truth_cls: np.ndarray, truth_xyz: np.ndarray,
                 gate_m: float = 0.5, reward: RewardConfig = RewardConfig()):
        self.N, self.C = int(n_slots), int(n_classes)
        self.truth_cls = np.asarray(truth_cls, dtype=np.int64)
        self.truth_xyz = np.asarray(truth_xyz, dtype=np.float64).reshape(-1, 3)
        self.gate2 = float(gate_m) ** 2
        self.reward = reward
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
        self.ev_n = np.zeros(N, dtype=np.int64)
        self.cur = np.full(N, -1, dtype=np.int64)  # index of the current detection per slot
        self._present: list[int] = []
        self.dets: dict | None = None
        self.stage = 0
        self.dropped = 0  # detections with no free slot
        self.recycled = 0  # unlabelled slots given to a new candidate
        self.frame_no = 0
        self.last_seen = [-1] * N
        self.duplicates = 0  # second detections of a slot in one frame
        self.cost = self._cost()
        names = slot_features(self.C)
        self._col = {n: k for k, n in enumerate(names)}
        self._det0 = self._col["det_x"]
        self._lab0 = self._col["has_label"]
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
        for j in self._present:
            i = cur[j]
            x, y, z = xyz[i]
            o[j, 0] = 1.0
            o[j, b:b + 7] = (x, y, z, _bounded(belief[i]), float(fpr[i]), _bounded(dets["range_list"][i]), st)
            if self.has[j]:
                lx, ly, lz = self.label[j]
                o[j, self._lab0 + 6] = math.sqrt((x - lx) ** 2 + (y - ly) ** 2 + (z - lz) ** 2)

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
        self._obs[j] = 0.0
        self.recycled += 1
        return j

    # --- actions ---------------------------------------------------------------------------------
    def act(self, labels: np.ndarray) -> float:
        """Apply per-slot actions to the current detections; returns the decrease of the cost."""
        changed = []
        if not self._present:
            return 0.0
        dets = self.dets
        labels = labels.tolist() if hasattr(labels, "tolist") else list(labels)
        for j in self._present:
            a = labels[j]
            if a == IGNORE:
                continue
            i = int(self.cur[j])
            if a == REPLACE or not self.has[j]:
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
            if j not in self._labelled:
                self.has[j] = True
                self._labelled.add(j)
                bisect.insort(self._labelled_by_class.setdefault(int(self.cls[j]), []), j)  # id order, as score_labels
            changed.append(j)
        if not changed:
            return 0.0
        o, L = self._obs, self._lab0
        for j in changed:
            lx, ly, lz = self.label[j]
            o[j, L:L + 6] = (1.0, lx, ly, lz, math.log1p(self.ev_n[j]), _bounded(self.label_belief[j]))
        before = self.cost
        self.cost = self._cost(changed)
        return before - self.cost

    # --- cost / score ------------------------------------------------------------------------------
    def _cost(self, changed=()) -> float:
        """The map's cost, matching objects to labels as ``testbed.run.score_labels`` does: each true
        object in turn takes the nearest unused label of its class. ``changed``: slots whose label
        moved since the last call (their column of the distance table is recomputed)."""
        r = self.reward
        K = len(self.truth_cls)
        if not hasattr(self, "_D"):
            self._D = [[math.inf] * self.N for _ in range(K)]
            self._truth = self.truth_xyz.tolist()
            self._truth_cls = self.truth_cls.tolist()
        D = self._D
        for j in changed:
            lx, ly, lz = self.label[j].tolist()
            c = int(self.cls[j])
            best = math.inf
            for k in range(K):
                if self._truth_cls[k] == c:
                    tx, ty, tz = self._truth[k]
                    e = math.sqrt((tx - lx) ** 2 + (ty - ly) ** 2 + (tz - lz) ** 2)
                    best = min(best, e)
                else:
                    e = math.inf
                D[k][j] = e
            self.label_err[j] = best
        if not self._labelled:
            return K * r.missing_cost_m
        used = set()
        cost, matched = 0.0, 0
        by_class = self._labelled_by_class
        for k in range(K):
            row = D[k]
            best, m = math.inf, -1
            for j in by_class.get(self._truth_cls[k], ()):
                e = row[j]
                if e < best and j not in used:
                    best, m = e, j
            if m < 0:
                cost += r.missing_cost_m
                continue
            used.add(m)
            matched += 1
            cost += best + (r.false_label_penalty if best > FALSE_LABEL_M else 0.0)
        return cost + r.extra_label_penalty * (len(self._labelled) - matched)

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
    for k in ("cls", "xyz", "fpr", "belief", "range", "err"):
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
