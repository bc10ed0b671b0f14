"""The six object classes: dimensions from ``data/objects.toml``, procedural meshes and textures.

No meshes can be downloaded, so each object is built here: a cuboid (or the "E" shape, a union of
boxes inside its cuboid) as a Wavefront OBJ with UVs into a texture atlas that gives every face its
own pattern, colour and glyph. Distinct faces are what let DOPE tell the corners apart.

Generated files go to a cache folder (``$DOPESLAM_CACHE`` or ``~/.cache/dopeslam``); the content is a
pure function of the class spec, so it is the same on every machine.
"""
from __future__ import annotations

import hashlib
import os
try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11: the same parser, backported
    import tomli as tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from stack.errors import DopeSlamError
from stack.io import write_bytes

DATA_DIR = Path(__file__).parent / "data"
OBJECTS_TOML = DATA_DIR / "objects.toml"
CLASSES = ("OrangeJuice", "Yogurt", "Mustard", "Raisins", "Cookies", "E")

_AXES = {"+x": np.array([1.0, 0, 0]), "-x": np.array([-1.0, 0, 0]),
         "+y": np.array([0, 1.0, 0]), "-y": np.array([0, -1.0, 0]),
         "+z": np.array([0, 0, 1.0]), "-z": np.array([0, 0, -1.0])}


class CatalogError(DopeSlamError, ValueError):
    pass


@dataclass(frozen=True)
class ObjectSpec:
    cls: str
    dims: np.ndarray  # (3,) cuboid size x y z in metres
    up_axis: str
    face_axis: str
    colors: tuple
    label: str
    shape: str = "box"
    parts: tuple = field(default=())  # ((centre(3), half_extents(3)), ...) boxes in the object frame

    @property
    def upright_R(self) -> np.ndarray:
        """Rotation object -> world of the standing object with its face heading along world +x."""
        up, face = _AXES[self.up_axis], _AXES[self.face_axis]
        third = np.cross(up, face)  # object axis that maps to world +y
        # R maps face -> world x, third -> world y, up -> world z: its rows are face, third, up
        return np.stack([face, third, up], axis=0)

    def standing_pose(self, xyz_bottom_centre, yaw: float) -> np.ndarray:
        """T_world_obj for the object standing on a surface at ``xyz_bottom_centre``, face towards ``yaw``."""
        c, s = np.cos(yaw), np.sin(yaw)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        T = np.eye(4)
        T[:3, :3] = Rz @ self.upright_R
        half_height = 0.5 * float(np.abs(self.upright_R[2] @ self.dims))
        T[:3, 3] = np.asarray(xyz_bottom_centre, dtype=float) + [0, 0, half_height]
        return T

    @property
    def height(self) -> float:
        return float(np.abs(self.upright_R[2] @ self.dims))


def _e_parts(dims: np.ndarray) -> tuple:
    """The "E": a spine on the left (-x) and three arms to the right, extruded along z."""
    w, h, d = dims
    spine_w, arm_h = 0.3 * w, 0.18 * h
    parts = [((-w / 2 + spine_w / 2, 0.0, 0.0), (spine_w / 2, h / 2, d / 2))]
    x0 = -w / 2 + spine_w
    for y, length in ((h / 2 - arm_h / 2, w - spine_w), (0.0, 0.8 * (w - spine_w)), (-h / 2 + arm_h / 2, w - spine_w)):
        parts.append(((x0 + length / 2, y, 0.0), (length / 2, arm_h / 2, d / 2)))
    return tuple((np.array(c), np.array(e)) for c, e in parts)


def load_catalog(path: Path = OBJECTS_TOML) -> dict[str, ObjectSpec]:
    return dict(_load_catalog(str(path)))


@lru_cache(maxsize=4)
def _load_catalog(path: str) -> tuple:
    with open(path, "rb") as f:
        data = tomllib.load(f)
    out = []
    for cls, entry in data.get("classes", {}).items():
        try:
            dims = np.array(entry["dims"], dtype=float)
            if dims.shape != (3,) or np.any(dims <= 0):
                raise CatalogError(f"{path}: classes.{cls}.dims: expected three positive sizes, got {entry['dims']}")
            up, face = entry["up_axis"], entry["face_axis"]
            if up not in _AXES or face not in _AXES or abs(_AXES[up] @ _AXES[face]) > 0:
                raise CatalogError(f"{path}: classes.{cls}: up_axis/face_axis must be two perpendicular of {list(_AXES)}")
        except KeyError as exc:
            raise CatalogError(f"{path}: classes.{cls}: missing field {exc.args[0]}") from None
        shape = entry.get("shape", "box")
        parts = _e_parts(dims) if shape == "E" else ((np.zeros(3), dims / 2),)
        out.append((cls, ObjectSpec(cls, dims, up, face, tuple(map(tuple, entry["colors"])),
                                    entry.get("label", cls), shape, parts)))
    return tuple(out)


def cuboid_keypoints(dims) -> np.ndarray:
    """(9, 3) cuboid corners + centroid in DOPE order, object frame (x right, y top, z front)."""
    w, h, d = np.asarray(dims, dtype=float) / 2
    return np.array([
        [w, h, d], [-w, h, d], [-w, -h, d], [w, -h, d],      # front: TR, TL, BL, BR
        [w, h, -d], [-w, h, -d], [-w, -h, -d], [w, -h, -d],  # rear:  TR, TL, BL, BR
        [0.0, 0.0, 0.0],
    ])


# --- procedural assets -------------------------------------------------------------------------

# Atlas layout: 3 x 2 cells of CELL px; face order +x -x +y -y +z -z.
CELL = 128
FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
_GLYPHS = ("R", "L", "T", "B", "F", "K")


def cache_dir() -> Path:
    d = Path(os.environ.get("DOPESLAM_CACHE") or Path.home() / ".cache" / "dopeslam").expanduser() / "assets"
    d.mkdir(parents=True, exist_ok=True)
    return d


def _atomic_write(path: Path, data: bytes) -> None:
    write_bytes(path, data)


def _face_texture(spec: ObjectSpec, face_idx: int) -> np.ndarray:
    rng = np.random.default_rng(int(hashlib.sha1(f"{spec.cls}/{face_idx}".encode()).hexdigest()[:8], 16))
    base, accent, ink = (np.array(c, dtype=float) for c in spec.colors)
    shade = 0.75 + 0.25 * (face_idx % 3) / 2  # each face a different brightness
    img = np.empty((CELL, CELL, 3), dtype=np.uint8)
    img[:] = np.clip(base * shade, 0, 255).astype(np.uint8)[::-1]  # cv2 draws BGR
    if spec.shape == "E":
        # 3D-printed plastic: a single colour with a per-face stripe direction so the faces differ
        for k in range(0, CELL, 16):
            if face_idx % 2 == 0:
                cv2.line(img, (k, 0), (k, CELL), tuple(int(v) for v in (accent * shade)[::-1]), 2)
            else:
                cv2.line(img, (0, k), (CELL, k), tuple(int(v) for v in (accent * shade)[::-1]), 2)
    else:
        # a band in the accent colour at a face-specific position, random dots, the label and a glyph
        y0 = int(CELL * (0.15 + 0.12 * face_idx))
        cv2.rectangle(img, (0, y0), (CELL, y0 + CELL // 6), tuple(int(v) for v in accent[::-1]), -1)
        for _ in range(12):
            c = tuple(int(v) for v in rng.integers(0, 255, 3))
            cv2.circle(img, tuple(int(v) for v in rng.integers(0, CELL, 2)), int(rng.integers(3, 10)), c, -1)
        cv2.putText(img, spec.label[:7], (4, y0 + CELL // 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    tuple(int(v) for v in ink[::-1]), 1, cv2.LINE_AA)
    cv2.putText(img, _GLYPHS[face_idx], (CELL // 2 - 18, CELL - 16), cv2.FONT_HERSHEY_DUPLEX, 1.6,
                tuple(int(v) for v in ink[::-1]), 3, cv2.LINE_AA)
    cv2.rectangle(img, (0, 0), (CELL - 1, CELL - 1), tuple(int(v) for v in (ink * 0.5)[::-1]), 2)
    return img


def texture_atlas(spec: ObjectSpec) -> np.ndarray:
    atlas = np.zeros((2 * CELL, 3 * CELL, 3), dtype=np.uint8)
    for i in range(6):
        r, c = divmod(i, 3)
        atlas[r * CELL:(r + 1) * CELL, c * CELL:(c + 1) * CELL] = _face_texture(spec, i)
    return atlas


def _obj_text(spec: ObjectSpec) -> str:
    """OBJ of the spec's boxes; each face's UVs span the object's whole extent in that face's plane."""
    half = spec.dims / 2
    lines, vt_lines, vn_lines, f_lines = [], [], [], []
    nv = nt = 0
    for i, face in enumerate(FACES):
        n = _AXES[face]
        vn_lines.append("vn %g %g %g" % tuple(n))
    for centre, ext in spec.parts:
        for i, face in enumerate(FACES):
            axis = "xyz".index(face[1])
            sign = 1.0 if face[0] == "+" else -1.0
            a, b = [k for k in range(3) if k != axis]
            if sign < 0:
                a, b = b, a  # keep counter-clockwise winding seen from outside
            if axis == 1:
                a, b = b, a
            r, c = divmod(i, 3)
            quad = []
            for da, db in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.array(centre, dtype=float).copy()
                p[axis] += sign * ext[axis]
                p[a] += da * ext[a]
                p[b] += db * ext[b]
                lines.append("v %.6f %.6f %.6f" % tuple(p))
                ua = (p[a] + half[a]) / (2 * half[a])
                ub = (p[b] + half[b]) / (2 * half[b])
                u = (c + 0.02 + 0.96 * ua) / 3.0
                v = 1.0 - (r + 0.02 + 0.96 * (1 - ub)) / 2.0
                vt_lines.append("vt %.6f %.6f" % (u, v))
                quad.append((nv + 1, nt + 1))
                nv += 1
                nt += 1
            ni = i + 1
            f_lines.append("f " + " ".join(f"{v}/{t}/{ni}" for v, t in quad[:3]))
            f_lines.append("f " + " ".join(f"{v}/{t}/{ni}" for v, t in (quad[0], quad[2], quad[3])))
    return "\n".join([f"# {spec.cls} generated by sim/objects.py"] + lines + vt_lines + vn_lines + f_lines) + "\n"


def asset_paths(spec: ObjectSpec) -> tuple[Path, Path]:
    """(obj_path, png_path) for the spec, generating them on first use."""
    obj = _obj_text(spec)
    tex = texture_atlas(spec)
    key = hashlib.sha1(obj.encode() + tex.tobytes()).hexdigest()[:12]
    d = cache_dir()
    obj_path, png_path = d / f"{spec.cls}_{key}.obj", d / f"{spec.cls}_{key}.png"
    if not obj_path.exists():
        _atomic_write(obj_path, obj.encode())
    if not png_path.exists():
        ok, buf = cv2.imencode(".png", tex)
        _atomic_write(png_path, buf.tobytes())
    return obj_path, png_path


def spawn_object(client: int, spec: ObjectSpec, T_world_obj: np.ndarray, mass: float = 0.0) -> int:
    """Create the textured object in a PyBullet client; returns the body id."""
    import pybullet as p
    from scipy.spatial.transform import Rotation

    obj_path, png_path = asset_paths(spec)
    vis = p.createVisualShape(p.GEOM_MESH, fileName=str(obj_path), meshScale=[1, 1, 1], physicsClientId=client)
    shapes = [p.createCollisionShape(p.GEOM_BOX, halfExtents=list(e), physicsClientId=client) for _, e in spec.parts]
    if len(shapes) == 1 and not np.any(spec.parts[0][0]):
        col = shapes[0]
    else:
        col = p.createCollisionShapeArray([p.GEOM_BOX] * len(spec.parts),
                                          halfExtents=[list(e) for _, e in spec.parts],
                                          collisionFramePositions=[list(c) for c, _ in spec.parts],
                                          physicsClientId=client)
    quat = Rotation.from_matrix(T_world_obj[:3, :3]).as_quat()
    body = p.createMultiBody(mass, col, vis, list(T_world_obj[:3, 3]), list(quat), physicsClientId=client)
    tex = p.loadTexture(str(png_path), physicsClientId=client)
    p.changeVisualShape(body, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=client)
    return body
