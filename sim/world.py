"""Builds a scenario's static world in a PyBullet client: floor, walls, ceiling, furniture, stands, objects.

Everything static is a box (objects are unions of boxes), recorded in ``World.boxes`` so the LiDAR's
analytic ray caster sees exactly the geometry that PyBullet renders and collides with.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import cv2
import numpy as np
import pybullet as p

from sim.objects import ObjectSpec, _atomic_write, cache_dir, load_catalog, spawn_object
from sim.scenario import Scenario
from stack.messages import ObjectTruth
from stack.transforms import make_T


@dataclass
class Box:
    """A static oriented box: T_world_box (centre) and half extents; reflectivity for LiDAR intensity."""

    T_world_box: np.ndarray
    half: np.ndarray
    reflectivity: float = 0.5
    name: str = ""


@dataclass
class World:
    client: int
    scenario: Scenario
    boxes: list[Box] = field(default_factory=list)
    objects: list[ObjectTruth] = field(default_factory=list)
    object_bodies: dict[str, int] = field(default_factory=dict)
    specs: dict[str, ObjectSpec] = field(default_factory=dict)


def _texture(kind: str, color, seed: int) -> str:
    """A procedural texture file (tiles for floors, panels + posters for walls, wood grain for furniture)."""
    key = hashlib.sha1(f"{kind}/{tuple(color)}/{seed}".encode()).hexdigest()[:12]
    path = cache_dir() / f"tex_{kind}_{key}.png"
    if path.exists():
        return str(path)
    rng = np.random.default_rng(int(key, 16) % (2**32))
    base = np.array(color[::-1], dtype=float)
    img = np.empty((256, 256, 3), dtype=np.float32)
    img[:] = base
    if kind == "floor":
        for i in range(8):
            for j in range(8):
                img[i * 32:(i + 1) * 32, j * 32:(j + 1) * 32] *= 0.85 + 0.3 * rng.random()
        img[::32, :] *= 0.6
        img[:, ::32] *= 0.6
    elif kind == "wall":
        for _ in range(6):  # posters: distinct features for place recognition
            x, y = rng.integers(0, 200, 2)
            w, h = rng.integers(20, 56, 2)
            img[y:y + h, x:x + w] = rng.integers(20, 235, 3)
            cv2.line(img, (int(x), int(y)), (int(x + w), int(y + h)), tuple(float(v) for v in rng.integers(0, 255, 3)), 2)
    else:
        img *= (0.9 + 0.1 * np.sin(np.arange(256) / rng.uniform(3, 9)))[:, None, None]
    img += rng.normal(0, 4, img.shape)
    ok, buf = cv2.imencode(".png", np.clip(img, 0, 255).astype(np.uint8))
    _atomic_write(path, buf.tobytes())
    return str(path)


def _add_box(world: World, centre, half, yaw: float, color, name: str, texture: str | None = None) -> int:
    c = world.client
    quat = p.getQuaternionFromEuler([0, 0, yaw])
    col = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half), physicsClientId=c)
    vis = p.createVisualShape(p.GEOM_BOX, halfExtents=list(half), rgbaColor=[1, 1, 1, 1] if texture else
                              [v / 255 for v in color] + [1], physicsClientId=c)
    body = p.createMultiBody(0, col, vis, list(centre), quat, physicsClientId=c)
    if texture:
        tex = p.loadTexture(texture, physicsClientId=c)
        p.changeVisualShape(body, -1, textureUniqueId=tex, physicsClientId=c)
    T = make_T(np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3), centre)
    world.boxes.append(Box(T, np.asarray(half, dtype=float), float(np.mean(color)) / 255, name))
    return body


def build_world(client: int, sc: Scenario) -> World:
    world = World(client, sc)
    catalog = load_catalog()
    room = sc.room
    hx, hy = room.size[0] / 2, room.size[1] / 2
    t, H = room.wall_thickness, room.wall_height
    # floor (its top at z = 0) and the walls, ceiling
    floor = _add_box(world, [0, 0, -0.05], [hx + t, hy + t, 0.05], 0, room.floor_color, "floor",
                     _texture("floor", room.floor_color, 0))
    p.changeDynamics(floor, -1, lateralFriction=1.0, physicsClientId=client)
    walls = [([hx + t / 2, 0, H / 2], [t / 2, hy + t, H / 2]), ([-hx - t / 2, 0, H / 2], [t / 2, hy + t, H / 2]),
             ([0, hy + t / 2, H / 2], [hx + t, t / 2, H / 2]), ([0, -hy - t / 2, H / 2], [hx + t, t / 2, H / 2])]
    for i, (cen, half) in enumerate(walls):
        _add_box(world, cen, half, 0, room.wall_color, f"wall_{i}", _texture("wall", room.wall_color, i))
    if room.ceiling:
        _add_box(world, [0, 0, H + 0.05], [hx + t, hy + t, 0.05], 0, [230, 230, 230], "ceiling")
    for i, f in enumerate(sc.furniture):
        sx, sy, sz = f.size
        name = f.name or f"furniture_{i}"
        yaw = np.radians(f.yaw_deg)
        if f.kind == "table":  # a top and four legs
            top = 0.04
            _add_box(world, [*f.position, sz - top / 2], [sx / 2, sy / 2, top / 2], yaw, f.color, name + "_top",
                     _texture("wood", f.color, i))
            c, s = np.cos(yaw), np.sin(yaw)
            for dx, dy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                lx, ly = dx * (sx / 2 - 0.04), dy * (sy / 2 - 0.04)
                _add_box(world, [f.position[0] + c * lx - s * ly, f.position[1] + s * lx + c * ly, (sz - top) / 2],
                         [0.025, 0.025, (sz - top) / 2], yaw, f.color, name + "_leg")
        else:
            _add_box(world, [*f.position, sz / 2], [sx / 2, sy / 2, sz / 2], yaw, f.color, name,
                     _texture("wood" if f.kind in ("shelf", "stand") else "panel", f.color, i))
    for o in sc.objects:
        spec = catalog[o.cls]
        yaw = np.radians(o.yaw_deg)
        if o.height > 0 and o.stand:
            # a slim stand under the object, a little smaller than its footprint
            foot = np.abs(spec.standing_pose([0, 0, 0], yaw)[:3, :3] @ spec.dims)
            half = [max(0.02, 0.4 * foot[0]), max(0.02, 0.4 * foot[1]), o.height / 2]
            _add_box(world, [*o.position, o.height / 2], half, 0.0, [60, 60, 60], f"stand_{o.name}")
        T = spec.standing_pose([*o.position, o.height], yaw)
        body = spawn_object(client, spec, T)
        for centre, half in spec.parts:
            Tb = T @ make_T(None, centre)
            world.boxes.append(Box(Tb, np.asarray(half), 0.6, o.name))
        world.objects.append(ObjectTruth(o.name, o.cls, T, spec.dims.copy()))
        world.object_bodies[o.name] = body
        world.specs[o.name] = spec
    return world
