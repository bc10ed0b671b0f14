"""Baseline labelling policies for the labelling envs.

A policy maps ``(observation, info)`` to an action; the ``oracle-*`` ones read the ground-truth
errors in ``info`` (the paper's hand-picked best and worst cases), the others only the observation.

=================  ==========================================================================
``last``           the paper's original rule: every detection replaces the label, even a false one
``last-fpr``       the paper's FPR: every detection that passed FPR replaces the label
``best-score``     a detection that passed FPR replaces the label when its belief sum is lower
                   (more certain) than the one the label rests on
``robust-mean``    every FPR-passing detection is fused: the label is the robust mean of them
``evidence``       the stack's publishing rule (``stack.evidence``): every FPR-passing detection
                   joins the slot's evidence, and the slot is published (fused) only while its
                   evidence meets ``EvidenceConfig`` (enough FPR-passing detections over a time
                   span and from more than one viewpoint, the cuboid above the floor, not outvoted
                   by another class at its place); otherwise it is withdrawn and stays a candidate
``oracle-best``    ground truth: a detection replaces the label when it is nearer the true object,
                   never when it would be a false label (> 0.25 m); per object the best detection
``oracle-worst``   ground truth: a detection replaces the label when it is further from the true
                   object; per object the worst detection
=================  ==========================================================================
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from stack.evidence import EvidenceConfig
from testbed.envs.slots import FUSE, IGNORE, REPLACE, WITHDRAW, slot_features
from testbed.scoring import FALSE_LABEL_M


class Columns:
    """Column indices of the ``slots`` observation for ``n_classes`` classes."""

    def __init__(self, n_classes: int):
        names = slot_features(n_classes)
        for k, name in enumerate(names):
            setattr(self, name, k)


class Policy:
    """Base: ``act(obs, info)`` -> action array for the env's action space."""

    name = "policy"
    uses_ground_truth = False

    def __init__(self, n_classes: int, extra_actions: int = 0, extra_default=None):
        self.c = Columns(n_classes)
        self.extra = extra_actions
        self.extra_default = list(extra_default or [0] * extra_actions)

    def reset(self) -> None:
        pass

    def labels(self, slots: np.ndarray, info: dict) -> np.ndarray:
        raise NotImplementedError

    def act(self, obs: dict, info: dict) -> np.ndarray:
        a = self.labels(obs["slots"], info).astype(np.int64)
        if self.extra:
            a = np.concatenate([a, np.asarray(self.extra_default, dtype=np.int64)])
        return a

    __call__ = act


class Last(Policy):
    name = "last"

    def labels(self, s, info):
        return np.where(s[:, self.c.present] > 0, REPLACE, IGNORE)


class LastFpr(Policy):
    name = "last-fpr"

    def labels(self, s, info):
        return np.where((s[:, self.c.present] > 0) & (s[:, self.c.det_fpr] > 0), REPLACE, IGNORE)


class BestScore(Policy):
    name = "best-score"

    def labels(self, s, info):
        c = self.c
        ok = (s[:, c.present] > 0) & (s[:, c.det_fpr] > 0)
        better = (s[:, c.has_label] == 0) | (s[:, c.det_belief] < s[:, c.label_belief])
        return np.where(ok & better, REPLACE, IGNORE)


class RobustMean(Policy):
    name = "robust-mean"

    def labels(self, s, info):
        return np.where((s[:, self.c.present] > 0) & (s[:, self.c.det_fpr] > 0), FUSE, IGNORE)


class Evidence(Policy):
    """Publishes what the stack's ``EvidenceConfig`` would publish, from the slots' evidence columns.

    The class vote is read from the slot's lead over the strongest other class at its place: the
    slot stays published while no other class there has more FPR-passing detections (a tie keeps it).
    """

    name = "evidence"

    def __init__(self, n_classes: int, extra_actions: int = 0, extra_default=None,
                 evidence: EvidenceConfig | None = None):
        super().__init__(n_classes, extra_actions, extra_default)
        self.evidence = evidence or EvidenceConfig()

    def publishable(self, s: np.ndarray) -> np.ndarray:
        """Per slot: does its evidence meet the stack's rule?"""
        c, e = self.c, self.evidence
        return ((s[:, c.ev_fpr_detections] >= e.min_observations) & (s[:, c.ev_span_s] >= e.min_span_s)
                & (s[:, c.ev_view_angle_deg] >= e.min_view_angle_deg)
                & (s[:, c.ev_floor_clearance_m] >= -e.floor_tolerance_m) & (s[:, c.ev_vote_lead] >= 0.5))

    def labels(self, s, info):
        c = self.c
        ok = self.publishable(s)
        passing = (s[:, c.present] > 0) & (s[:, c.det_fpr] > 0)
        short = (s[:, c.has_label] > 0) & ~ok
        return np.where(passing, np.where(ok, FUSE, WITHDRAW), np.where(short, WITHDRAW, IGNORE))


class OracleBest(Policy):
    name = "oracle-best"
    uses_ground_truth = True

    def labels(self, s, info):
        det, lab = info["detection_error_m"], info["label_error_m"]
        nearer = (lab < 0) | (det < lab)
        ok = (s[:, self.c.present] > 0) & (det >= 0) & (det <= FALSE_LABEL_M)
        return np.where(ok & nearer, REPLACE, IGNORE)


class OracleWorst(Policy):
    name = "oracle-worst"
    uses_ground_truth = True

    def labels(self, s, info):
        det, lab = info["detection_error_m"], info["label_error_m"]
        further = (lab < 0) | (det > lab)
        return np.where((s[:, self.c.present] > 0) & (det >= 0) & further, REPLACE, IGNORE)


BASELINES: dict[str, Callable[..., Policy]] = {p.name: p for p in (Last, LastFpr, BestScore, RobustMean,
                                                                    Evidence, OracleBest, OracleWorst)}
PAPER_NAMES = {"last": "original", "last-fpr": "fpr", "oracle-best": "best", "oracle-worst": "worst"}


def make_policy(name: str, env) -> Policy:
    """A baseline for ``env`` (its class count and any extra action entries, e.g. the stage choice,
    which baselines leave at the env's configured stage count; ``evidence`` takes the env's
    ``evidence_cfg``, by default ``EvidenceConfig()``)."""
    if name not in BASELINES:
        raise KeyError(f"unknown baseline {name!r}; expected one of {sorted(BASELINES)}")
    base = env.unwrapped
    n_classes = len(base.classes)
    nvec = base.action_space.nvec if hasattr(base.action_space, "nvec") else None
    extra = 0 if nvec is None else len(nvec) - base.N
    default = []
    if extra and getattr(base, "stage_choice", False):
        default = [base.stage_options.index(base.stages) if base.stages in base.stage_options else len(base.stage_options) - 1]
    if BASELINES[name] is Evidence:
        return Evidence(n_classes, extra, default, getattr(base, "evidence_cfg", None))
    return BASELINES[name](n_classes, extra, default)


def run_episode(env, policy: Policy, options: dict | None = None, seed: int | None = None) -> dict:
    """One episode of ``policy``; returns the final map score, return and step count."""
    obs, info = env.reset(seed=seed, options=options)
    policy.reset()
    total, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, info = env.step(policy(obs, info))
        total += reward
        steps += 1
        if terminated or truncated:
            break
    return {"return": total, "steps": steps, **info.get("map_score", {}), "episode": info.get("episode")}
