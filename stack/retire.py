"""Retiring labels whose object is gone: negative evidence from the depth image.

Each image (once the odometry has a pose at its stamp) is checked against every map object the
stack holds: is the object's centroid inside the camera's view, within range, and what does the
aligned depth image show there?

- nearer than the object's front by more than the tolerance: something stands in front of it
  (occluded): no evidence either way;
- about where the object's surface should be: something is there: no evidence against it (a
  detector that missed it is no reason to drop it);
- further than the object's back by more than the tolerance: the camera sees through the place
  where the object was: the place is **empty**, one miss.

A detection in the image associated with the object that passed FPR is a sighting and clears its
misses (one FPR rejected is no evidence either way). After
``misses`` empty views (and at least ``min_span_s`` between the first and the last) the object is
retired: its row stays in the store with status ``retired`` and it is no label. An object seen
again after that (``revive_sightings`` detections associated with it) comes back: its observations start afresh (the earlier ones are kept in
``past``), so the label is where it is now. Hand-edited rows are never retired.

The checker knows nothing of where the images come from: a pose, intrinsics and a depth image.
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from stack.messages import CameraInfo

RETIRED = "retired"
PRESENT_SHARE = 0.15  # this much of the object's image at its depth: something is there
SEEN, EMPTY, OCCLUDED, PRESENT, OUT_OF_VIEW, NO_DEPTH = "seen", "empty", "occluded", "present", "out_of_view", "no_depth"


class RetireConfig(BaseModel):
    """How much negative evidence retires a label (``DopeSlam(retire=...)``)."""

    model_config = ConfigDict(extra="forbid")

    misses: int = Field(8, ge=1, description="empty views of an object's place before it is retired")
    min_span_s: float = Field(0.5, ge=0.0, description="seconds between the first and the last of them")
    min_range_m: float = Field(0.35, ge=0.0, description="the object's centroid at least this far from the camera")
    max_range_m: float = Field(2.5, gt=0.0, description="... and at most this far (depth noise grows as z^2)")
    margin_px: float = Field(12.0, ge=0.0, description="the centroid at least this far inside the image")
    tolerance_m: float = Field(0.08, gt=0.0, description="depth beyond the object's extent that counts as "
                               "in front of it (occluded) or behind it (empty)")
    min_observations: int = Field(3, ge=1, description="objects with fewer observations are not checked")
    revive_sightings: int = Field(3, ge=1, description="detections of a retired object that bring it back "
                                  "(fewer leave it retired)")


@dataclass
class MissCount:
    misses: int = 0
    first: float = math.nan
    last: float = math.nan


def classify(xyz_map: np.ndarray, size: np.ndarray, T_map_cam: np.ndarray, info: CameraInfo,
             depth_m: np.ndarray | None, config: RetireConfig) -> str:
    """What one image says about the object whose centroid is at ``xyz_map`` (cuboid ``size``):
    one of ``empty``, ``occluded``, ``present``, ``out_of_view``, ``no_depth``."""
    R, t = T_map_cam[:3, :3], T_map_cam[:3, 3]
    p = R.T @ (np.asarray(xyz_map, dtype=float) - t)  # camera optical frame
    z = float(p[2])
    if not config.min_range_m <= float(np.linalg.norm(p)) <= config.max_range_m or z <= 0:
        return OUT_OF_VIEW
    u, v = info.fx * p[0] / z + info.cx, info.fy * p[1] / z + info.cy
    m = config.margin_px
    if not (m <= u <= info.width - 1 - m and m <= v <= info.height - 1 - m):
        return OUT_OF_VIEW
    return depth_verdict(u, v, z, size, info, depth_m, config.tolerance_m)


def depth_verdict(u: float, v: float, z: float, size, info: CameraInfo, depth_m: np.ndarray | None,
                  tolerance_m: float) -> str:
    """What the depth image shows about a cuboid of ``size`` whose centroid projects to pixel (u, v) at
    depth ``z`` (the camera's intrinsics ``info``; the depth image may be smaller): ``present``,
    ``occluded``, ``empty`` or ``no_depth``."""
    if depth_m is None:
        return NO_DEPTH
    scale = depth_m.shape[1] / info.width
    r = max(2, int(0.5 * float(np.min(size)) * info.fx / z * scale))  # about the object's own image
    uu, vv = int(round(u * scale)), int(round(v * scale))
    win = depth_m[max(0, vv - r):vv + r + 1, max(0, uu - r):uu + r + 1]
    valid = win[win > 0]
    if valid.size < max(3, win.size // 4):
        return NO_DEPTH
    extent = 0.5 * float(np.linalg.norm(size))  # the cuboid's half diagonal: its surface is within this of z
    front = valid < z - extent - tolerance_m
    back = valid > z + extent + tolerance_m
    if 1.0 - front.mean() - back.mean() >= PRESENT_SHARE:
        return PRESENT  # something at the object's depth: no evidence against it
    if front.mean() >= 0.5:
        return OCCLUDED
    if back.mean() >= 0.5:
        return EMPTY
    return PRESENT


class Retirement:
    """Counts each map object's empty views and retires it; ``view(...)`` once per posed image."""

    def __init__(self, config: RetireConfig | None = None):
        self.config = config or RetireConfig()
        self.counts: dict[int, MissCount] = {}
        self.views = 0
        self.retired: list[tuple[int, float]] = []  # (object id, stamp) in the order they were retired
        self.verdicts: dict[str, int] = {}

    def view(self, store, T_map_cam: np.ndarray, info: CameraInfo, depth_m: np.ndarray | None,
             seen_ids: Iterable[int], stamp: float) -> list[int]:
        """One image's evidence on every object of ``store``; returns the ids retired by it."""
        self.views += 1
        seen = set(seen_ids)
        out = []
        for obj in store:
            if obj.edited:
                continue
            if obj.status == RETIRED:  # its place seen empty again: the sightings so far were strays
                if obj.sightings and obj.id not in seen and \
                        classify(obj.xyz, obj.size, T_map_cam, info, depth_m, self.config) == EMPTY:
                    obj.sightings.clear()
                continue
            c = self.counts.setdefault(obj.id, MissCount())
            if obj.id in seen:
                self.counts[obj.id] = MissCount()
                self._tally(SEEN)
                continue
            if len(obj.history) < self.config.min_observations and obj.history:
                continue
            verdict = classify(obj.xyz, obj.size, T_map_cam, info, depth_m, self.config)
            self._tally(verdict)
            if verdict != EMPTY:
                continue
            if c.misses == 0:
                c.first = stamp
            c.misses += 1
            c.last = stamp
            if c.misses >= self.config.misses and abs(c.last - c.first) >= self.config.min_span_s:
                retire(obj, f"place seen empty in {c.misses} images from t = {c.first:.1f} s to {c.last:.1f} s",
                       self.config.revive_sightings)
                self.retired.append((obj.id, stamp))
                out.append(obj.id)
        return out

    def _tally(self, verdict: str) -> None:
        self.verdicts[verdict] = self.verdicts.get(verdict, 0) + 1

    def summary(self) -> dict:
        return {"views": self.views, "retired": [{"id": i, "stamp": s} for i, s in self.retired],
                "verdicts": dict(self.verdicts), "config": self.config.model_dump()}


def retire(obj, reason: str, revive_after: int = 3) -> None:
    obj.status, obj.reason, obj.revive_after, obj.sightings = RETIRED, reason, int(revive_after), []


def carry_over(old_store, new_store, revive_after: int = 3) -> int:
    """After every observation was fused again into ``new_store`` (a loop closure placed the map
    anew), retire each new object whose observations are mostly those of an object retired in
    ``old_store``: what the depth images showed empty stays retired. Returns how many were."""
    def key(h) -> tuple[float, str]:
        return (float(h.stamp), str(h.cls))

    gone: dict[tuple[float, str], object] = {}
    for obj in old_store:
        if obj.status == RETIRED:
            for h in list(obj.history) + list(getattr(obj, "sightings", [])):
                gone[key(h)] = obj
    count = 0
    for obj in new_store:
        if obj.edited or not obj.history:
            continue
        hits = [gone[key(h)] for h in obj.history if key(h) in gone]
        if 2 * len(hits) > len(obj.history):
            retire(obj, hits[0].reason, revive_after)
            count += 1
    return count


def revive(obj) -> None:
    """A retired object seen again: it comes back, its label from what is seen from now on."""
    obj.past = list(getattr(obj, "past", [])) + list(obj.history)
    obj.history = []
    obj.status, obj.reason = "candidate", "seen again after it was retired"
