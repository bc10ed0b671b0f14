"""World events: objects moved, removed or added during an episode, and people walking through.

A scenario's optional ``[[events]]`` list (validated with the rest of the scenario)::

    [[events]]
    kind = "move"                # move | remove | add | walk
    object = "Mustard"           # move / remove: the object's name
    at = 20.0                    # not before this time (s)
    robot_farther_than = 3.0     # and only once the robot is this far (m) from `near`
    near = [1.6, -0.55]          # (default: where the object is; for add / walk: the first point)
    to = [1.1, 0.55]             # move: the new bottom centre x y (add: `position`)
    height = 0.30                # move / add: height of the surface it stands on
    yaw_deg = 200                # move / add: the direction its front face looks
    stand = true                 # move / add: a stand under it when height > 0

    [[events]]
    kind = "walk"                # a person-sized box walking a path (camera and LiDAR both see it)
    path = [[3.0, -2.0], [3.0, 2.0]]
    speed = 1.0
    loop = true                  # back and forth along the path (else it stays at the end)
    size = [0.45, 0.30, 1.70]

An event happens at the first physics step at which all its conditions hold. Ground truth follows
every event: :class:`WorldEvents` keeps each object's pose history (``truth_at``), and the LiDAR's
ray caster is rebuilt from the world's boxes when they change (a walker is cast where it stands at
the end of each sweep).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from stack.messages import ObjectTruth
from stack.transforms import make_T

Vec2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
PERSON_COLOR = [205, 150, 120]


class Event(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    kind: Literal["move", "remove", "add", "walk"]
    object: str = Field("", description="move / remove: the object's name; add: the new object's name")
    cls: str = Field("", alias="class", description="add: the object's class")
    at: float = Field(0.0, ge=0.0, description="seconds: the event happens no earlier")
    robot_farther_than: float | None = Field(None, gt=0.0, description="metres from `near`")
    near: Vec2 | None = None
    to: Vec2 | None = Field(None, description="move: the new bottom centre x y")
    position: Vec2 | None = Field(None, description="add: bottom centre x y")
    height: float = Field(0.0, ge=0.0, le=3.0)
    yaw_deg: float = 0.0
    stand: bool = True
    path: list[Vec2] = Field(default_factory=list, description="walk: points x y the person walks through")
    speed: float = Field(1.0, gt=0.0, le=3.0, description="walk: m/s")
    loop: bool = False
    size: Vec3 = Field([0.45, 0.30, 1.70], description="walk: the person's box x y z (m)")

    @model_validator(mode="after")
    def _fields_of_kind(self):
        need = {"move": ("object", "to"), "remove": ("object",), "add": ("cls", "position"), "walk": ("path",)}
        for f in need[self.kind]:
            if not getattr(self, f):
                raise ValueError(f"a '{self.kind}' event needs '{'class' if f == 'cls' else f}'")
        if self.kind == "walk" and len(self.path) < 2:
            raise ValueError("a 'walk' event needs a path of at least 2 points")
        if min(self.size) <= 0:
            raise ValueError("size: expected three positive sizes in metres")
        return self


def check_events(sc) -> None:
    """Cross-checks against the scenario: names exist (or are added first), points in the room.
    Raises ValueError naming ``events.I.field``."""
    hx, hy = sc.room.size[0] / 2, sc.room.size[1] / 2
    names = {o.name or o.cls for o in sc.objects}
    for i, e in enumerate(sc.events):
        for f in ("to", "position", "near"):
            xy = getattr(e, f)
            if xy is not None and not (abs(xy[0]) < hx and abs(xy[1]) < hy):
                raise ValueError(f"events.{i}.{f}: {xy} is outside the room (|x| < {hx}, |y| < {hy})")
        for k, xy in enumerate(e.path):
            if not (abs(xy[0]) < hx and abs(xy[1]) < hy):
                raise ValueError(f"events.{i}.path.{k}: {xy} is outside the room (|x| < {hx}, |y| < {hy})")
        if e.kind == "add":
            e.object = e.object or e.cls
            if e.object in names:
                raise ValueError(f"events.{i}.object: an object named {e.object!r} already exists")
            names.add(e.object)
        elif e.kind in ("move", "remove") and e.object not in names:
            raise ValueError(f"events.{i}.object: expected one of {sorted(names)}, got {e.object!r}")


@dataclass
class Walker:
    event: Event
    body: int
    box_index: int
    start: float | None = None  # when it started walking
    xy: np.ndarray = field(default_factory=lambda: np.zeros(2))
    heading: float = 0.0

    def place_at(self, s: float) -> None:
        """Put the walker ``s`` metres along its path (back and forth when looping)."""
        pts = np.asarray(self.event.path, dtype=float)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        total = float(seg.sum())
        forward = True
        if self.event.loop and total > 0:
            s = s % (2 * total)
            if s > total:
                s, forward = 2 * total - s, False
        s = min(max(s, 0.0), total)
        i = int(np.searchsorted(np.cumsum(seg), s, side="right")) if total > 0 else 0
        i = min(i, len(seg) - 1)
        f = (s - float(np.sum(seg[:i]))) / max(seg[i], 1e-9)
        self.xy = pts[i] + f * (pts[i + 1] - pts[i])
        d = pts[i + 1] - pts[i]
        h = math.atan2(d[1], d[0]) + (0.0 if forward else math.pi)
        self.heading = (h + math.pi) % (2 * math.pi) - math.pi


class WorldEvents:
    """Applies a scenario's events to a built ``sim.world.World`` as time goes on.

    ``step(t, robot_xy)`` is called once per physics step; it returns True when the world's boxes
    changed (the LiDAR's caster must be rebuilt). ``log``: what happened, in order.
    """

    def __init__(self, world, events):
        import pybullet as p

        self.world = world
        self.client = world.client
        self.pending = [e for e in events if e.kind != "walk"]
        self.walkers: list[Walker] = []
        self.log: list[dict] = []
        self.truth: dict[str, list[tuple[float, ObjectTruth | None]]] = {
            o.name: [(0.0, o)] for o in world.objects}
        from sim.world import Box, _add_box  # noqa: F401 (the same boxes the world is built of)

        for i, e in enumerate(x for x in events if x.kind == "walk"):
            half = [s / 2 for s in e.size]
            body = _add_box(world, [*e.path[0], half[2]], half, 0.0, PERSON_COLOR, f"person_{i}")
            p.setCollisionFilterGroupMask(body, -1, 0, 0, physicsClientId=self.client)  # walks through the robot
            w = Walker(e, body, len(world.boxes) - 1)
            w.place_at(0.0)
            self._place_walker(w)
            self.walkers.append(w)

    @property
    def person_bodies(self) -> set[int]:
        return {w.body for w in self.walkers}

    @property
    def person_boxes(self) -> set[int]:
        return {w.box_index for w in self.walkers}

    def _due(self, e: Event, t: float, robot_xy) -> bool:
        if t < e.at:
            return False
        if e.robot_farther_than is None:
            return True
        near = e.near
        if near is None:
            if e.kind in ("move", "remove"):
                T = self.world_object(e.object)
                near = T.T_world_obj[:2, 3] if T is not None else e.to
            else:
                near = e.position if e.kind == "add" else e.path[0]
        return math.hypot(robot_xy[0] - near[0], robot_xy[1] - near[1]) > e.robot_farther_than

    def world_object(self, name: str) -> ObjectTruth | None:
        return next((o for o in self.world.objects if o.name == name), None)

    def step(self, t: float, robot_xy) -> bool:
        changed = False
        for e in list(self.pending):
            if self._due(e, t, robot_xy):
                self.pending.remove(e)
                self._apply(e, t)
                changed = True
        for w in self.walkers:
            if w.start is None and self._due(w.event, t, robot_xy):
                w.start = t
                self.log.append({"t": t, "kind": "walk", "path": w.event.path})
            if w.start is not None:
                w.place_at((t - w.start) * w.event.speed)
                self._place_walker(w)
                changed = True
        return changed

    def _place_walker(self, w: Walker) -> None:
        import pybullet as p

        half = self.world.boxes[w.box_index].half
        centre = [float(w.xy[0]), float(w.xy[1]), float(half[2])]
        c, s = math.cos(w.heading), math.sin(w.heading)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        self.world.boxes[w.box_index].T_world_box = make_T(R, centre)
        p.resetBasePositionAndOrientation(w.body, centre, p.getQuaternionFromEuler([0, 0, w.heading]),
                                          physicsClientId=self.client)

    def _apply(self, e: Event, t: float) -> None:
        import pybullet as p

        from sim.objects import load_catalog, spawn_object
        from sim.world import _add_box

        world = self.world
        if e.kind in ("move", "remove"):
            old = self.world_object(e.object)
            body = world.object_bodies.pop(e.object)
            p.removeBody(body, physicsClientId=self.client)
            world.boxes[:] = [b for b in world.boxes if b.name != e.object]
            world.objects[:] = [o for o in world.objects if o.name != e.object]
            spec = world.specs[e.object]
            entry = {"t": t, "kind": e.kind, "object": e.object, "cls": old.cls,
                     "from_xyz": [float(v) for v in old.T_world_obj[:3, 3]]}
        else:
            spec = load_catalog()[e.cls]
            world.specs[e.object] = spec
            entry = {"t": t, "kind": "add", "object": e.object, "cls": e.cls}
        if e.kind == "remove":
            self.truth[e.object].append((t, None))
            self.log.append(entry)
            self._reindex_walkers()
            return
        xy = e.to if e.kind == "move" else e.position
        yaw = math.radians(e.yaw_deg)
        if e.height > 0 and e.stand:
            foot = np.abs(spec.standing_pose([0, 0, 0], yaw)[:3, :3] @ spec.dims)
            half = [max(0.02, 0.4 * foot[0]), max(0.02, 0.4 * foot[1]), e.height / 2]
            _add_box(world, [*xy, e.height / 2], half, 0.0, [60, 60, 60], f"stand_{e.object}_{len(self.log)}")
        T = spec.standing_pose([*xy, e.height], yaw)
        world.object_bodies[e.object] = spawn_object(self.client, spec, T)
        for centre, half in spec.parts:
            world.boxes.append(type(world.boxes[0])(T @ make_T(None, centre), np.asarray(half), 0.6, e.object))
        truth = ObjectTruth(e.object, spec.cls, T, spec.dims.copy())
        world.objects.append(truth)
        self.truth.setdefault(e.object, []).append((t, truth))
        entry["to_xyz"] = [float(v) for v in T[:3, 3]]
        self.log.append(entry)
        # walkers' boxes keep their indices: they were added before any event, objects' boxes after
        self._reindex_walkers()

    def _reindex_walkers(self) -> None:
        names = [b.name for b in self.world.boxes]
        for i, w in enumerate(self.walkers):
            w.box_index = names.index(f"person_{i}")

    def truth_at(self, t: float) -> list[ObjectTruth]:
        """The objects in the world at time ``t`` (their poses then)."""
        out = []
        for states in self.truth.values():
            now = [s for ts, s in states if ts <= t]
            if now and now[-1] is not None:
                out.append(now[-1])
        return out

    def past_positions(self) -> list[tuple[str, str, np.ndarray]]:
        """(name, class, centroid) of every place an object stood and no longer stands."""
        out = []
        for name, states in self.truth.items():
            for k, (_, s) in enumerate(states):
                if s is not None and k < len(states) - 1:
                    out.append((name, s.cls, s.T_world_obj[:3, 3].copy()))
        return out
