"""Scenario files: TOML, validated. Every error names the file, the field and what was expected.

A scenario declares the room and its furniture, the objects (class, position, yaw, height / stand),
the robot's start pose, the route (waypoints, speeds, pauses), the light level, sensor settings and
the seed. ``extends = "other.toml"`` (a file in the same folder) takes another scenario as the base
and overrides its tables key by key; lists (furniture, objects) are replaced whole.
"""
from __future__ import annotations

import re
try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11: the same parser, backported
    import tomli as tomllib
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import (BaseModel, ConfigDict, Field, ValidationError, field_validator, model_serializer,
                      model_validator)

from sim.events import Event, check_events
from sim.faults import Faults
from stack.errors import DopeSlamError
from stack.io import read_user_text

SCENES_DIR = Path(__file__).parent / "scenes"
DEFAULT_SCENARIO = "experiment3_columns"

Vec2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Color = Annotated[list[Annotated[int, Field(ge=0, le=255)]], Field(min_length=3, max_length=3)]


# An ``[expect]`` value: a comparison with a number (checked against the run's report by ``dopeslam test``).
EXPECT_COMPARISON = re.compile(r"^\s*(>=|<=|==|!=|>|<)\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|true|false)\s*$")


class ScenarioError(DopeSlamError, ValueError):
    """A scenario file that cannot be used; the message names file, field and expectation."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # every number finite


class Room(_Strict):
    size: Vec2 = Field(description="inner size x, y in metres; the room is centred on the world origin")
    wall_height: float = Field(2.6, gt=0.5, le=20)
    wall_thickness: float = Field(0.15, gt=0.01, le=2)
    ceiling: bool = True
    wall_color: Color = [200, 196, 185]
    floor_color: Color = [120, 110, 100]

    @field_validator("size")
    @classmethod
    def _positive(cls, v):
        if min(v) <= 1.0 or max(v) > 200:
            raise ValueError("expected two sizes between 1 and 200 m")
        return v


class Furniture(_Strict):
    name: str = ""
    kind: Literal["box", "pillar", "shelf", "table", "stand"] = "box"
    position: Vec2 = Field(description="centre on the floor, x y in metres")
    size: Vec3 = Field(description="x y z extent in metres")
    yaw_deg: float = 0.0
    color: Color = [150, 150, 150]

    @field_validator("size")
    @classmethod
    def _size(cls, v):
        if min(v) <= 0:
            raise ValueError("expected three positive sizes in metres")
        return v


class SceneObject(_Strict):
    cls: str = Field(alias="class")
    name: str = ""
    position: Vec2 = Field(description="x y of the object's bottom centre in metres")
    height: float = Field(0.0, ge=0.0, le=3.0, description="height of the surface it stands on (m)")
    yaw_deg: float = Field(0.0, description="direction its front face looks, degrees in world")
    stand: bool = Field(True, description="put a stand under it when height > 0")


class Robot(_Strict):
    start: Vec3 = Field(description="x, y (m) and yaw (deg) of base_link in world")


class Route(_Strict):
    waypoints: list[Annotated[list[float], Field(min_length=2, max_length=3)]] = Field(
        min_length=1, description="[x, y] or [x, y, speed m/s]")
    speed: float = Field(0.3, gt=0.0, le=2.0)
    start_pause: float = Field(0.0, ge=0.0, description="seconds standing still before driving")
    pauses: list[Vec2] = Field(default_factory=list, description="[waypoint index, seconds]")
    tolerance: float = Field(0.05, gt=0.0, le=1.0, description="a waypoint is reached within this distance")

    @field_validator("waypoints")
    @classmethod
    def _speeds(cls, v):
        for w in v:
            if len(w) == 3 and not 0 < w[2] <= 2.0:
                raise ValueError("a waypoint speed must be in (0, 2.0] m/s (the Jackal's maximum)")
        return v


class Sensors(_Strict):
    camera: bool = True
    camera_rate: float = Field(10.0, gt=0.0, le=60.0)
    camera_width: int = Field(640, ge=32, le=1920)
    camera_height: int = Field(480, ge=24, le=1080)
    lidar: bool = True
    lidar_rate: float = Field(10.0, ge=1.0, le=30.0)
    lidar_azimuth_steps: int = Field(1808, ge=16, le=8192)
    lidar_packets: bool = Field(False, description="the Velodyne publishes VLP-32C data packets (ranges in 4 mm "
                                "steps, 0.01 deg block azimuths, the lasers' azimuth offsets) and each sweep is "
                                "their decoding; a bag records the packets (velodyne_msgs/VelodyneScan)")
    wheel_odometry_rate: float = Field(20.0, gt=0.0, le=200.0)
    noise: bool = True

    @model_serializer(mode="wrap")
    def _omit_points_lidar(self, handler):
        """``lidar_packets`` is left out of dumps while off, so a scenario without it dumps (and so
        hashes: the perception cache's key) as it did before the field existed."""
        data = handler(self)
        if isinstance(data, dict) and not self.lidar_packets:
            data.pop("lidar_packets", None)
        return data


class Scenario(_Strict):
    name: str
    description: str = ""
    seed: int = Field(0, ge=0)
    duration: float = Field(60.0, gt=0.0, le=3600.0)
    light: float = Field(1.0, ge=0.0, le=1.0, description="1 = lit, 0 = complete darkness")
    light_schedule: list[Vec2] = Field(default_factory=list, description="[time s, level]: from that time on the "
                                       "light is at that level (before the first entry: `light`)")
    physics_hz: float = Field(240.0, ge=60.0, le=1000.0)
    room: Room
    furniture: list[Furniture] = Field(default_factory=list)
    objects: list[SceneObject] = Field(default_factory=list)
    robot: Robot
    route: Route
    sensors: Sensors = Field(default_factory=Sensors)
    events: list[Event] = Field(default_factory=list, description="objects moved, removed, added; people "
                                "walking (sim/events.py)")
    faults: Faults = Field(default_factory=Faults, description="sensor faults (sim/faults.py)")
    extends: str | None = None
    expect: dict[str, bool | int | float | str] = Field(
        default_factory=dict, description='"dotted.path.in.report.json" = "OP NUMBER" (>=, <=, >, <, ==, !=), '
        'plus min_pass_rate (0-1) over seeds; see docs/testing.md')
    source: str = Field("", exclude=True)

    @field_validator("expect")
    @classmethod
    def _expect(cls, v):
        for key, value in v.items():
            if key == "min_pass_rate":
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 1:
                    raise ValueError(f"expect '{key}': expected a number from 0 to 1, got {value!r}")
            elif isinstance(value, str) and not EXPECT_COMPARISON.match(value):
                raise ValueError(f"expect '{key}': expected a comparison such as \">= 6\" or \"<= 0.05\", got {value!r}")
        return v

    @model_validator(mode="after")
    def _inside_room(self):
        hx, hy = self.room.size[0] / 2, self.room.size[1] / 2
        def inside(xy):
            return abs(xy[0]) < hx and abs(xy[1]) < hy
        for i, o in enumerate(self.objects):
            if not inside(o.position):
                raise ValueError(f"objects.{i}.position {o.position} is outside the room (|x| < {hx}, |y| < {hy})")
        for i, f in enumerate(self.furniture):
            if not inside(f.position):
                raise ValueError(f"furniture.{i}.position {f.position} is outside the room (|x| < {hx}, |y| < {hy})")
        if not inside(self.robot.start[:2]):
            raise ValueError(f"robot.start {self.robot.start[:2]} is outside the room (|x| < {hx}, |y| < {hy})")
        for i, w in enumerate(self.route.waypoints):
            if not inside(w[:2]):
                raise ValueError(f"route.waypoints.{i} {w[:2]} is outside the room (|x| < {hx}, |y| < {hy})")
        for i, (t, level) in enumerate(self.light_schedule):
            if not 0.0 <= level <= 1.0 or t < 0 or (i and t <= self.light_schedule[i - 1][0]):
                raise ValueError(f"light_schedule.{i}: expected [time s >= 0, increasing; level 0..1], got {[t, level]}")
        for i, (idx, secs) in enumerate(self.route.pauses):
            if not (0 <= idx < len(self.route.waypoints)) or int(idx) != idx or secs < 0:
                raise ValueError(f"route.pauses.{i}: expected [waypoint index 0..{len(self.route.waypoints) - 1}, seconds >= 0]")
        return self

    @model_validator(mode="after")
    def _geometry(self):
        check_geometry(self)
        return self

    @property
    def object_names(self) -> list[str]:
        return [o.name for o in self.objects]


ROBOT_RADIUS_M = 0.26  # the Jackal's footprint (0.42 x 0.31 m chassis, wheels inside) as a circle
WAYPOINT_CLEARANCE_M = 0.15  # a waypoint this near furniture is unreachable without touching it


def _footprint(f: Furniture) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre, unit axes (2 x 2, rows) and half sizes of a piece of furniture on the floor."""
    yaw = np.radians(f.yaw_deg)
    axes = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    return np.asarray(f.position, dtype=float), axes, np.asarray(f.size[:2], dtype=float) / 2


def _inside(f: Furniture, xy, margin: float = 0.0) -> bool:
    """Whether the floor point ``xy`` lies within ``margin`` of the furniture's footprint (or in it)."""
    c, axes, half = _footprint(f)
    local = np.abs(axes @ (np.asarray(xy[:2], dtype=float) - c))
    gap = np.maximum(local - half, 0.0)
    return bool(np.hypot(*gap) < margin) if margin > 0 else bool(np.all(local < half))


def check_geometry(sc: "Scenario") -> None:
    """A world that can be built and driven: furniture within the room and under its ceiling, the
    robot's start and the route's waypoints clear of furniture, objects not buried inside
    furniture and not inside each other. Raises ValueError naming the field."""
    hx, hy = sc.room.size[0] / 2, sc.room.size[1] / 2
    for i, f in enumerate(sc.furniture):
        c, axes, half = _footprint(f)
        corners = c + np.array([[sx, sy] for sx in (-1, 1) for sy in (-1, 1)]) * half @ axes
        wall = sc.room.wall_thickness  # furniture may stand against a wall, reaching into it
        if np.any(np.abs(corners[:, 0]) > hx + wall) or np.any(np.abs(corners[:, 1]) > hy + wall):
            raise ValueError(f"furniture.{i} ({f.name or f.kind}): its footprint reaches outside the room "
                             f"(|x| <= {hx}, |y| <= {hy}, walls {wall} m thick)")
        if f.size[2] > sc.room.wall_height:
            raise ValueError(f"furniture.{i} ({f.name or f.kind}): height {f.size[2]} m is above the walls "
                             f"({sc.room.wall_height} m)")
    start = sc.robot.start
    if abs(start[0]) > hx - ROBOT_RADIUS_M or abs(start[1]) > hy - ROBOT_RADIUS_M:
        raise ValueError(f"robot.start {start[:2]}: the robot ({ROBOT_RADIUS_M} m) would stand in a wall")
    for i, f in enumerate(sc.furniture):
        if _inside(f, start, ROBOT_RADIUS_M):
            raise ValueError(f"robot.start {start[:2]}: the robot ({ROBOT_RADIUS_M} m) would stand inside "
                             f"furniture.{i} ({f.name or f.kind})")
        for j, w in enumerate(sc.route.waypoints):
            if _inside(f, w, WAYPOINT_CLEARANCE_M):
                raise ValueError(f"route.waypoints.{j} {w[:2]}: within {WAYPOINT_CLEARANCE_M} m of (or inside) "
                                 f"furniture.{i} ({f.name or f.kind})")
    for k, o in enumerate(sc.objects):
        for i, f in enumerate(sc.furniture):
            if f.kind in ("box", "pillar") and _inside(f, o.position) and o.height < f.size[2] - 0.01:
                raise ValueError(f"objects.{k} ({o.cls}): at height {o.height} m inside furniture.{i} "
                                 f"({f.name or f.kind}, {f.size[2]} m tall); put it on top (height = {f.size[2]})")
        for m in range(k):
            q = sc.objects[m]
            if abs(q.height - o.height) < 0.05 and np.hypot(o.position[0] - q.position[0],
                                                             o.position[1] - q.position[1]) < 0.05:
                raise ValueError(f"objects.{k} ({o.cls}) and objects.{m} ({q.cls}) stand in the same place")


def with_overrides(sc: "Scenario", *, seed: int | None = None, duration: float | None = None,
                   light: float | None = None) -> "Scenario":
    """``sc`` with command-line overrides, validated by the same model as the file: ScenarioError
    names the option and what was expected (``--light 5``, ``--duration nan``, ``--seed -1``)."""
    given = {k: v for k, v in (("seed", seed), ("duration", duration), ("light", light)) if v is not None}
    if not given:
        return sc
    data = {**sc.model_dump(by_alias=True, exclude={"source"}), **given}
    if "light" in given:
        data["light_schedule"] = []  # an override wins over the schedule
    try:
        out = Scenario.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = str(err["loc"][0]) if err["loc"] else ""
        if key in given:
            raise ScenarioError(f"--{key} {given[key]}: {err['msg']}") from None
        loc = ".".join(str(x) for x in err["loc"])
        raise ScenarioError(f"{sc.source or sc.name}: field '{loc}': {err['msg']} (with --{' --'.join(given)})") from None
    for a, b in zip(out.objects, sc.objects):
        a.name = b.name
    out.source = sc.source
    return out


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _read_toml(path: Path, depth: int = 0) -> dict:
    text = read_user_text(path, ScenarioError, "a scenario TOML file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from None
    parent = data.get("extends")
    if parent is not None:
        if depth > 4:
            raise ScenarioError(f"{path}: field 'extends': chain longer than 5 files")
        if not isinstance(parent, str):
            raise ScenarioError(f"{path}: field 'extends': expected a file name in the same folder")
        base_path = (path.parent / parent).resolve()
        if base_path.parent != path.parent.resolve():
            raise ScenarioError(f"{path}: field 'extends': expected a file in the same folder, got {parent!r}")
        data = _merge(_read_toml(base_path, depth + 1), data)
    return data


def resolve_path(name_or_path: str | Path | None) -> Path:
    """A bundled scenario's name, or a path to a TOML file."""
    if name_or_path is None:
        name_or_path = DEFAULT_SCENARIO
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        return p
    bundled = SCENES_DIR / f"{name_or_path}.toml"
    if bundled.exists():
        return bundled
    raise ScenarioError(f"{name_or_path}: no such scenario file, and no bundled scenario of that name "
                        f"(bundled: {', '.join(bundled_scenarios())})")


def load_scenario(name_or_path: str | Path | None = None) -> Scenario:
    from sim.objects import load_catalog

    path = resolve_path(name_or_path)
    data = _read_toml(path)
    try:
        sc = Scenario.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"]) or "(top level)"
        got = f" (got {err['input']!r})" if "input" in err and not isinstance(err["input"], dict) else ""
        raise ScenarioError(f"{path}: field '{loc}': {err['msg']}{got}") from None
    catalog = load_catalog()
    for i, o in enumerate(sc.objects):
        if o.cls not in catalog:
            raise ScenarioError(f"{path}: field 'objects.{i}.class': expected one of {sorted(catalog)}, got {o.cls!r}")
        if not o.name:
            o.name = o.cls if sum(x.cls == o.cls for x in sc.objects) == 1 else f"{o.cls}_{i}"
    names = [o.name for o in sc.objects]
    if len(set(names)) != len(names):
        raise ScenarioError(f"{path}: field 'objects': object names must be unique, got {names}")
    for i, e in enumerate(sc.events):
        if e.kind == "add" and e.cls not in catalog:
            raise ScenarioError(f"{path}: field 'events.{i}.class': expected one of {sorted(catalog)}, got {e.cls!r}")
    try:
        check_events(sc)
    except ValueError as exc:
        field, _, msg = str(exc).partition(": ")
        raise ScenarioError(f"{path}: field '{field}': {msg}") from None
    sc.source = str(path)
    return sc


def bundled_scenarios() -> list[str]:
    return sorted(p.stem for p in SCENES_DIR.glob("*.toml"))


def default_scenario_path() -> Path:
    return SCENES_DIR / f"{DEFAULT_SCENARIO}.toml"
