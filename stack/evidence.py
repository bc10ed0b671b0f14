"""Which map objects are published as labels, and which stay candidates.

Every detection that reaches the map starts or feeds a map object, but a label is a claim to the
map's user that an object of that class is there. A false label costs more than a missing one (the
paper's point: "only the best object labels end up on the map"), so an object is published only on
consistent evidence, judged with what the robot itself knows:

- **enough evidence**: FPR-passing observations, over a time span and from more than one viewpoint
  (one view can repeat the same mistake in every frame; a real object stays put as the camera moves);
- **detected when in view** (rules off by default): each object counts the images that showed its
  place (``views``, :func:`count_views`, from the robot's pose, intrinsics and depth). With
  ``min_detection_rate`` an object detected in too few of them stays a candidate; with
  ``quick_observations`` one detected in most of them is published on fewer observations (an object
  passed at speed). Measured on the bundled scenes, a repeatable false detection is seen as often as a
  real object passed at speed, so neither rule is on unless a user turns it on;
- **physically possible**: its cuboid does not reach below the floor plane that the LiDAR odometry
  fits, and the observations it rests on were taken within the camera's range;
- **one object per place**: map objects of different classes whose labels lie closer than two real
  objects can stand are one physical object seen as several classes (the depth network's typical
  error is a wrong class on a right object); the class with the most evidence there wins the vote,
  and only with at least ``vote_share`` of the place's observations (else the classes disagree and
  no label there would be more than a guess).

Everything else stays in the store as a candidate, saved with its reason (the ``status`` and
``reason`` columns), so a person or a policy can look at it, but it is not a label.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from stack.messages import CameraInfo
from stack.retire import EMPTY, PRESENT, RETIRED, depth_verdict

LABEL = "label"
CANDIDATE = "candidate"


class EvidenceConfig(BaseModel):
    """What a map object needs before it is published as a label."""

    model_config = ConfigDict(extra="forbid")

    min_observations: int = Field(5, ge=1, description="FPR-passing observations within range")
    min_span_s: float = Field(1.0, ge=0, description="time between the first and last of them")
    min_view_angle_deg: float = Field(3.0, ge=0, description="largest angle between two of their viewing rays")
    floor_tolerance_m: float = Field(0.04, ge=0, description="how far the cuboid may reach below the floor")
    max_range_m: float = Field(10.0, gt=0, description="observations from further away are no evidence (D435i)")
    vote_radius_m: float = Field(0.12, ge=0, description="labels of different classes this near are one object")
    vote_share: float = Field(0.5, ge=0, le=1, description="the winning class's share of the evidence at its place")
    min_detection_rate: float = Field(0.0, ge=0, le=1, description="observations per image that showed its place: "
                                      "fewer keep it a candidate (judged from rate_min_views views on)")
    rate_min_views: int = Field(10, ge=1, description="views before the detection rate is judged")
    quick_observations: int = Field(0, ge=0, description="an object detected in at least quick_detection_rate of "
                                    "its views needs only this many observations and no time span (0: off)")
    quick_detection_rate: float = Field(0.6, ge=0, le=1, description="see quick_observations")


@dataclass
class Evidence:
    """What one map object rests on (from its FPR-passing observations within range)."""

    observations: int
    span_s: float
    view_angle_deg: float  # nan when no observation carries its viewpoint
    floor_height_m: float  # height of the cuboid's lowest corner above the floor; nan without a floor
    views: int = 0  # detected images that showed its place (0: not counted)

    @property
    def detection_rate(self) -> float:
        """Observations per image that showed its place (nan when no views were counted)."""
        return min(1.0, self.observations / self.views) if self.views else math.nan


def evidence_of(obj, config: EvidenceConfig, floor: tuple[np.ndarray, float] | None) -> Evidence:
    """``obj``: a ``MapObject`` (label pose, size and observation history; an observation that stands
    for several in a thinned history counts its ``weight``)."""
    obs = [o for o in obj.history if o.fpr_pass and not (o.range_m > config.max_range_m)]
    stamps = [o.stamp for o in obs]
    span = float(max(stamps) - min(stamps)) if stamps else 0.0
    return Evidence(sum(getattr(o, "weight", 1) for o in obs), span, view_angle_deg(obj.xyz, [o.cam_xyz for o in obs if o.cam_xyz is not None]),
                    lowest_corner_height(obj.xyz, obj.quat_xyzw, obj.size, floor), int(getattr(obj, "views", 0)))


def view_angle_deg(xyz, cam_positions: Sequence[np.ndarray]) -> float:
    """The largest angle (deg) between two viewing rays from the cameras to ``xyz``."""
    if not cam_positions:
        return math.nan
    rays = np.asarray(xyz, dtype=float) - np.asarray(cam_positions, dtype=float)
    norms = np.linalg.norm(rays, axis=1)
    rays = rays[norms > 1e-9] / norms[norms > 1e-9, None]
    if len(rays) < 2:
        return 0.0
    # The widest pair includes a ray at an extreme of the spread: test against the mean direction's
    # furthest ray, then the furthest from that one (exact for rays within a half-space, which views are).
    mean = rays.mean(axis=0)
    a = rays[np.argmin(rays @ mean)]
    b = rays[np.argmin(rays @ a)]
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def lowest_corner_height(xyz, quat_xyzw, size, floor: tuple[np.ndarray, float] | None) -> float:
    """Height above the floor plane (n, d; n.x + d = height) of the cuboid's lowest corner."""
    if floor is None:
        return math.nan
    n, d = floor
    R = Rotation.from_quat(np.asarray(quat_xyzw, dtype=float)).as_matrix()
    half_extent = 0.5 * float(np.abs(R.T @ n) @ np.asarray(size, dtype=float))
    return float(n @ np.asarray(xyz, dtype=float) + d - half_extent)


def assess(objects: Sequence, config: EvidenceConfig, floor: tuple[np.ndarray, float] | None
           ) -> dict[int, tuple[str, str, Evidence]]:
    """Per object id: (status, reason, evidence), judged from each object's observation history."""
    result: dict[int, tuple[str, str, Evidence]] = {}
    contenders = []
    for obj in objects:
        ev = evidence_of(obj, config, floor)
        reason = _too_weak(ev, config)
        result[obj.id] = (CANDIDATE, reason, ev) if reason else (LABEL, "", ev)
        if ev.observations:
            contenders.append(obj)
    _vote(contenders, result, config)
    return result


def _too_weak(ev: Evidence, config: EvidenceConfig) -> str:
    rate = ev.detection_rate
    if ev.views >= config.rate_min_views and rate < config.min_detection_rate:
        return f"detected in {ev.observations} of {ev.views} images that showed it (needs {config.min_detection_rate:.0%})"
    quick = 0 < config.quick_observations <= ev.observations and rate >= config.quick_detection_rate
    if ev.observations < config.min_observations and not quick:
        return f"{ev.observations} observations (needs {config.min_observations})"
    if ev.span_s < config.min_span_s and not quick:
        return f"seen over {ev.span_s:.2f} s (needs {config.min_span_s:g} s)"
    if not math.isnan(ev.view_angle_deg) and ev.view_angle_deg < config.min_view_angle_deg:
        return f"seen from one viewpoint ({ev.view_angle_deg:.1f} deg, needs {config.min_view_angle_deg:g} deg)"
    if ev.floor_height_m < -config.floor_tolerance_m:
        return f"reaches {-100 * ev.floor_height_m:.0f} cm below the floor"
    return ""


def _vote(objects: Sequence, result: dict, config: EvidenceConfig) -> None:
    """Objects of different classes at one place: the most supported wins; the others become candidates.
    A winner without ``vote_share`` of the place's evidence is a candidate too: the classes disagree
    there, and a label would be a guess.

    Every object with evidence takes part (a candidate's observations still say what is there), and
    the strongest claims are settled first, so a weak object never knocks out a strong one.
    """
    def support(o) -> int:
        return result[o.id][2].observations

    def near(a, b) -> bool:
        return a.cls != b.cls and np.linalg.norm(np.asarray(a.xyz) - np.asarray(b.xyz)) < config.vote_radius_m

    order = sorted(objects, key=lambda o: (-support(o), o.id))
    winners: list = []
    for obj in order:
        beaten_by = next((w for w in winners if near(w, obj)), None)
        if beaten_by is None:
            winners.append(obj)
        elif result[obj.id][0] == LABEL:
            ev = result[obj.id][2]
            result[obj.id] = (CANDIDATE, f"outvoted at its place by {beaten_by.cls} #{beaten_by.id} "
                                         f"({support(beaten_by)} vs {ev.observations})", ev)
    for w in winners:
        total = support(w) + sum(support(o) for o in objects if near(w, o))
        if result[w.id][0] == LABEL and support(w) < config.vote_share * total:
            ev = result[w.id][2]
            result[w.id] = (CANDIDATE, f"classes disagree at its place ({support(w)} of {total} observations "
                                       f"are {w.cls}; needs {config.vote_share:.0%})", ev)


# --- views: how often an object's place was in view --------------------------------------------------

VIEW_MIN_RANGE_M = 0.3  # nearer than this the object fills the image: no view either way
VIEW_RANGE_SLACK = 1.1  # in view up to this times the furthest range it was detected at
VIEW_MARGIN_PX = 12.0  # the centroid at least this far inside the image
VIEW_TOLERANCE_M = 0.08  # depth nearer than the object's front by more than this: occluded, no view


def count_views(objects: Sequence, T_map_cam: np.ndarray, info: CameraInfo, depth_m: np.ndarray | None,
                seen: Sequence[int] = ()) -> int:
    """One detected image's views: each map object (not retired) whose place the image shows gets one more
    ``views``. Shown: seen in the image (an FPR-passing detection associated with it, ids in ``seen``),
    or its centroid inside the image, within the distances it has been detected at, and the depth image
    there not nearer than its front (what the robot itself sees: its pose, intrinsics and depth; an
    image without depth shows only what was seen in it). A real object is detected in much of the
    images that show it; a false one, a reflection of one view, in few. Returns the views counted."""
    seen = set(seen)
    objs = [o for o in objects if o.status != RETIRED and o.history]
    if not objs:
        return 0
    xyz = np.array([o.xyz for o in objs], dtype=float).reshape(-1, 3)
    R, t = np.asarray(T_map_cam, dtype=float)[:3, :3], np.asarray(T_map_cam, dtype=float)[:3, 3]
    p = (xyz - t) @ R  # camera optical frame
    z = p[:, 2]
    rng = np.linalg.norm(p, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = info.fx * p[:, 0] / z + info.cx
        v = info.fy * p[:, 1] / z + info.cy
    m = VIEW_MARGIN_PX
    inside = (z > 0) & (rng >= VIEW_MIN_RANGE_M) & (u >= m) & (u <= info.width - 1 - m) \
        & (v >= m) & (v <= info.height - 1 - m)
    counted = 0
    for i, obj in enumerate(objs):
        if obj.id in seen:
            obj.views += 1
            counted += 1
            continue
        if not inside[i] or depth_m is None:
            continue
        far = detected_range(obj)
        if not rng[i] <= VIEW_RANGE_SLACK * far:
            continue
        if depth_verdict(float(u[i]), float(v[i]), float(z[i]), obj.size, info, depth_m,
                         VIEW_TOLERANCE_M) in (PRESENT, EMPTY):
            obj.views += 1
            counted += 1
    return counted


def detected_range(obj) -> float:
    """The furthest range at which an FPR-passing observation saw ``obj`` (nan when none did)."""
    far = getattr(obj, "view_range_m", math.nan)
    if math.isnan(far):
        ranges = [o.range_m for o in obj.history if o.fpr_pass and math.isfinite(o.range_m)]
        if ranges:
            far = float(max(ranges))
            obj.view_range_m = far
    return far


def carry_views(old_objects: Sequence, new_objects: Sequence) -> None:
    """After observations were fused again into new objects (a loop closure placed the map anew, or a
    saved store was published again), each new object takes the views of the old object that held the
    most of its observations (the images that showed a place do not change when the place moves by
    centimetres)."""
    owner: dict[tuple[float, str], object] = {}
    for obj in old_objects:
        for h in obj.history:
            owner[(float(h.stamp), str(h.cls))] = obj
    for obj in new_objects:
        votes: dict[int, list] = {}
        for h in obj.history:
            old = owner.get((float(h.stamp), str(h.cls)))
            if old is not None:
                votes.setdefault(old.id, [old, 0])[1] += 1
        if votes:
            old, _ = max(votes.values(), key=lambda e: (e[1], -e[0].id))
            obj.views = int(old.views)
