"""Synthetic DOPE training data from our own renderer (the testbed's NDDS).

Each image: one to three of the six object classes standing upright on stands, shelves or the
floor, 0.3-1.8 m from a camera at the Jackal's camera height looking roughly horizontally, in a
domain-randomised room: textured floor and walls, random textured boxes as distractors and
occluders, other objects as distractors, random light direction, colour and strength.

Images are rendered at the D435i's 640x480 and area-downscaled to ``--size`` (default 320x240,
DOPE's inference resolution here), so training pixels look like the ones the detector sees.
Depth gets the D435i noise model (sim.camera) at 640x480 and is downscaled by nearest neighbour.

Output: shards ``shard_NNNNN.npz`` (rgb uint8 (N,H,W,3), depth_mm uint16 (N,H,W), seg int16 (N,H,W):
-1 background, k = the k-th annotated object, 99 distractor) and ``shard_NNNNN.json`` with, per image,
the camera intrinsics at the saved size and per object: class, keypoints_px (9x2, DOPE order, at the
saved size), location (m, camera optical frame), quaternion (x, y, z, w), pixel counts and in-frame flags.
"""
from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from sim.camera import DepthNoise, apply_color_noise, apply_depth_noise, default_camera_info, gl_matrices, hardware
from sim.objects import CLASSES, cuboid_keypoints, load_catalog, spawn_object
from stack.io import atomic_path, write_json

log = logging.getLogger(__name__)
FAR_AWAY = np.array([0.0, 0.0, -50.0])
DISTRACTOR_SEG = 99


@dataclass
class DatagenConfig:
    out_dir: Path
    n_images: int = 4000
    shard_size: int = 50
    seed: int = 0
    workers: int = 2
    width: int = 320
    height: int = 240
    dist_range: tuple = (0.3, 1.8)
    cam_height: tuple = (0.25, 0.45)
    classes: tuple = CLASSES
    slim_stand_prob: float = 0.5  # an object on a stand stands on a slim one (80 % of its footprint, as the
    # scenarios' object stands are) this often, else on a wide box; in depth the slim stand and the object
    # merge into one column, which the network must have seen


def _random_texture(rng: np.random.Generator, size: int = 64) -> np.ndarray:
    kind = rng.integers(0, 5)
    c1, c2 = rng.integers(0, 256, 3), rng.integers(0, 256, 3)
    yy, xx = np.mgrid[0:size, 0:size]
    if kind == 0:  # checker
        k = int(rng.integers(4, 17))
        m = ((yy // k + xx // k) % 2).astype(bool)
    elif kind == 1:  # stripes
        k = int(rng.integers(3, 13))
        m = ((xx if rng.random() < 0.5 else yy) // k % 2).astype(bool)
    elif kind == 2:  # blobs (smoothed noise)
        n = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), float(rng.uniform(1, 6)))
        m = n > np.median(n)
    elif kind == 3:  # plain
        m = np.zeros((size, size), bool)
    else:  # random noise
        img = rng.integers(0, 256, (size, size, 3)).astype(np.uint8)
        return cv2.GaussianBlur(img, (0, 0), float(rng.uniform(0.5, 2)))
    img = np.where(m[..., None], c1, c2).astype(np.uint8)
    return img


class _World:
    """A PyBullet client with reusable bodies: objects, distractor boxes, stands, floor and walls."""

    def __init__(self, rng: np.random.Generator, classes: tuple, tex_dir: Path):
        self.client = p.connect(p.DIRECT)
        self.rng = rng
        c = self.client
        self.textures = []
        for i in range(48):
            path = tex_dir / f"tex_{i}.png"
            cv2.imwrite(str(path), _random_texture(rng))
            self.textures.append(p.loadTexture(str(path), physicsClientId=c))
        self.catalog = load_catalog()
        self.classes = classes
        self.specs = [self.catalog[k] for k in classes]
        # two copies of every class: one can be a target and one a distractor of the same kind
        self.objects = []  # (class index, body)
        for ci, spec in enumerate(self.specs):
            for _ in range(2):
                T = np.eye(4)
                T[:3, 3] = FAR_AWAY
                self.objects.append((ci, spawn_object(c, spec, T)))
        self.boxes = [self._box(rng.uniform(0.03, 0.35, 3)) for _ in range(14)]
        self.stands = [self._box(np.array([rng.uniform(0.12, 0.5), rng.uniform(0.12, 0.5), 1.2])) for _ in range(4)]
        # one slim stand per class, 80 % of the object's footprint (its horizontal axes at yaw 0)
        self.slim_stands = []
        for spec in self.specs:
            foot = np.abs(spec.standing_pose([0, 0, 0], 0.0)[:3, :3] @ np.asarray(spec.dims, dtype=float))
            self.slim_stands.append(self._box(np.array([max(0.04, 0.8 * foot[0]), max(0.04, 0.8 * foot[1]), 1.2])))
        self.floor = self._box(np.array([12.0, 12.0, 0.1]))
        self.walls = [self._box(np.array([0.1, 12.0, 4.0])) for _ in range(3)]
        self.movable = [b for _, b in self.objects] + self.boxes + self.stands + self.slim_stands + self.walls

    def _box(self, size: np.ndarray) -> int:
        c = self.client
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=list(size / 2), physicsClientId=c)
        return p.createMultiBody(0, -1, vis, list(FAR_AWAY), physicsClientId=c)

    def _place(self, body: int, xyz, R: np.ndarray | None = None) -> None:
        q = [0, 0, 0, 1] if R is None else list(Rotation.from_matrix(R).as_quat())
        p.resetBasePositionAndOrientation(body, list(xyz), q, physicsClientId=self.client)

    def _retexture(self, body: int) -> None:
        rgba = list(self.rng.uniform(0.4, 1.0, 3)) + [1.0]
        p.changeVisualShape(body, -1, textureUniqueId=int(self.rng.choice(self.textures)), rgbaColor=rgba,
                            physicsClientId=self.client)

    def stage(self, cfg: DatagenConfig, info_full) -> tuple[np.ndarray, list]:
        """Arrange a new random scene; returns (T_world_cam, [(class index, body, T_world_obj, on_stand)])."""
        rng = self.rng
        for b in self.movable:
            self._place(b, FAR_AWAY)
        # floor and walls
        self._place(self.floor, [0, 0, -0.05])
        self._retexture(self.floor)
        half_fov = np.arctan(info_full.width / 2 / info_full.fx)
        hc = rng.uniform(*cfg.cam_height)
        # camera at the origin looking along +x (yaw random), pitch/roll noise
        yaw_c = rng.uniform(-np.pi, np.pi)
        pitch = np.deg2rad(rng.normal(0, 4))
        roll = np.deg2rad(rng.normal(0, 1.5))
        R_world_base = Rotation.from_euler("zyx", [yaw_c, pitch, roll]).as_matrix()
        R_base_opt = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # optical z fwd, x right, y down
        T_world_cam = np.eye(4)
        T_world_cam[:3, :3] = R_world_base @ R_base_opt
        T_world_cam[:3, 3] = [0, 0, hc]
        fwd = R_world_base[:, 0]
        left = R_world_base[:, 1]
        for wall in self.walls:
            if rng.random() < 0.75:
                d = rng.uniform(1.5, 6.0)
                ang = yaw_c + rng.uniform(-1.2, 1.2)
                Rz = Rotation.from_euler("z", ang).as_matrix()
                self._place(wall, [d * np.cos(ang), d * np.sin(ang), 2.0], Rz)
                self._retexture(wall)
        # target objects
        n_targets = int(rng.choice([1, 1, 2, 2, 3]))
        cls_choice = rng.choice(len(self.specs), size=n_targets, replace=False)
        placed = []
        stands = list(self.stands)
        rng.shuffle(stands)
        for ci in cls_choice:
            spec = self.specs[ci]
            body = [b for k, b in self.objects if k == ci][0]
            d = rng.uniform(*cfg.dist_range)
            bearing = rng.uniform(-half_fov * 0.85, half_fov * 0.85)
            v_half = np.arctan(info_full.height / 2 / info_full.fy) * 0.8
            lo = hc - np.tan(v_half) * d - spec.height * 0.5
            hi = hc + np.tan(v_half) * d - spec.height * 0.5
            zb = rng.uniform(max(0.0, lo), max(0.0, hi) + 1e-3)
            if rng.random() < 0.25 and lo < 0.0:
                zb = 0.0  # on the floor
            pos_h = np.array([0.0, 0.0, 0.0])
            direction = np.cos(bearing) * fwd + np.sin(-bearing) * left
            direction[2] = 0
            direction /= np.linalg.norm(direction)
            pos_h = direction * d
            yaw = rng.uniform(-np.pi, np.pi)
            T = spec.standing_pose([pos_h[0], pos_h[1], zb], yaw)
            self._place(body, T[:3, 3], T[:3, :3])
            on_stand = zb > 0.01 and stands
            # slim_stand_prob 0 makes no draw: the data of the earlier weights, exactly
            if on_stand and cfg.slim_stand_prob > 0 and rng.random() < cfg.slim_stand_prob:
                st = self.slim_stands[ci]  # under the object, turned with it
                self._place(st, [pos_h[0], pos_h[1], zb - 0.6], Rotation.from_euler("z", yaw).as_matrix())
                self._retexture(st)
            elif on_stand:
                st = stands.pop()
                # stands are 1.2 m tall: top at zb
                jitter = rng.uniform(-0.03, 0.03, 2)
                self._place(st, [pos_h[0] + jitter[0], pos_h[1] + jitter[1], zb - 0.6],
                            Rotation.from_euler("z", rng.uniform(-np.pi, np.pi)).as_matrix())
                self._retexture(st)
            placed.append((int(ci), body, T))
        # distractor objects of other classes (or the second copy)
        for ci, body in self.objects:
            if any(body == b for _, b, _ in placed):
                continue
            if rng.random() < 0.12:
                spec = self.specs[ci]
                d = rng.uniform(0.4, 3.0)
                bearing = rng.uniform(-half_fov, half_fov)
                direction = np.cos(bearing) * fwd - np.sin(bearing) * left
                direction[2] = 0
                direction /= np.linalg.norm(direction)
                zb = rng.uniform(0.0, 0.5)
                # the distractor copy is a true object of its class too: it must then be annotated
                T = spec.standing_pose([*(direction * d)[:2], zb], rng.uniform(-np.pi, np.pi))
                self._place(body, T[:3, 3], T[:3, :3])
                placed.append((int(ci), body, T))
        # distractor boxes (some in front of targets as occluders)
        for box in self.boxes:
            if rng.random() < 0.45:
                d = rng.uniform(0.35, 4.0)
                bearing = rng.uniform(-half_fov * 1.2, half_fov * 1.2)
                direction = np.cos(bearing) * fwd - np.sin(bearing) * left
                direction[2] = 0
                direction /= np.linalg.norm(direction)
                z = rng.uniform(0.0, 0.8)
                R = Rotation.from_euler("zyx", [rng.uniform(-np.pi, np.pi), rng.normal(0, 0.3), rng.normal(0, 0.3)]).as_matrix()
                self._place(box, [*(direction * d)[:2], z], R)
                self._retexture(box)
        return T_world_cam, placed

    def render(self, T_world_cam, info, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        view, proj = gl_matrices(T_world_cam, info)
        az, el = rng.uniform(-np.pi, np.pi), rng.uniform(0.2, 1.4)
        light_dir = [np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)]
        _, _, rgba, zbuf, seg = p.getCameraImage(
            info.width, info.height, view, proj, renderer=p.ER_TINY_RENDERER,
            lightDirection=light_dir, lightColor=list(rng.uniform(0.7, 1.0, 3)),
            lightAmbientCoeff=float(rng.uniform(0.3, 0.8)), lightDiffuseCoeff=float(rng.uniform(0.3, 0.8)),
            lightSpecularCoeff=float(rng.uniform(0.0, 0.3)), shadow=int(rng.random() < 0.3),
            physicsClientId=self.client)
        from sim.camera import FAR, NEAR
        rgb = np.asarray(rgba, np.uint8).reshape(info.height, info.width, 4)[..., :3]
        zb = np.asarray(zbuf, np.float64).reshape(info.height, info.width)
        depth = (FAR * NEAR / (FAR - (FAR - NEAR) * zb)).astype(np.float32)
        depth[zb >= 1.0] = 0.0
        segm = np.asarray(seg, np.int32).reshape(info.height, info.width)
        return rgb, depth, segm


def _atomic_save_npz(path: Path, **arrays) -> None:
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, **arrays)


def _atomic_save_json(path: Path, obj) -> None:
    write_json(path, obj, indent=None)


def generate_shard(cfg: DatagenConfig, shard: int) -> Path:
    """Render one shard (deterministic in (seed, shard)); returns the npz path."""
    out = Path(cfg.out_dir)
    npz_path = out / f"shard_{shard:05d}.npz"
    json_path = out / f"shard_{shard:05d}.json"
    if npz_path.exists() and json_path.exists():
        return npz_path
    rng = np.random.default_rng([cfg.seed, shard])
    info_full = default_camera_info()
    info = info_full.scaled(cfg.width, cfg.height)
    noise = DepthNoise.from_hardware()
    read_noise = hardware()["d435i"]["read_noise"]
    n = min(cfg.shard_size, cfg.n_images - shard * cfg.shard_size)
    with tempfile.TemporaryDirectory() as tex_dir:
        world = _World(rng, tuple(cfg.classes), Path(tex_dir))
        rgbs, depths, segs, annos = [], [], [], []
        try:
            for i in range(n):
                T_world_cam, placed = world.stage(cfg, info_full)
                rgb, depth, seg = world.render(T_world_cam, info_full, rng)
                light = float(rng.uniform(0.35, 1.3)) if rng.random() < 0.5 else 1.0
                rgb = apply_color_noise(rgb, light, read_noise, rng)
                depth = apply_depth_noise(depth, info_full, noise, rng)
                rgb_s = cv2.resize(rgb, (cfg.width, cfg.height), interpolation=cv2.INTER_AREA)
                depth_s = depth[1::2, 1::2] if (cfg.width * 2, cfg.height * 2) == (640, 480) else \
                    cv2.resize(depth, (cfg.width, cfg.height), interpolation=cv2.INTER_NEAREST)
                seg_s = seg[1::2, 1::2] if (cfg.width * 2, cfg.height * 2) == (640, 480) else \
                    cv2.resize(seg, (cfg.width, cfg.height), interpolation=cv2.INTER_NEAREST)
                seg_out = np.full(seg_s.shape, -1, np.int16)
                body_ids = seg_s & ((1 << 24) - 1)
                seg_out[(seg_s >= 0)] = DISTRACTOR_SEG
                seg_out[(seg_s >= 0) & (body_ids == world.floor)] = -1
                objs = []
                T_cam_world = np.linalg.inv(T_world_cam)
                for k, (ci, body, T_world_obj) in enumerate(placed):
                    spec = world.specs[ci]
                    T_cam_obj = T_cam_world @ T_world_obj
                    if T_cam_obj[2, 3] < 0.1:
                        continue
                    pts = cuboid_keypoints(spec.dims) @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
                    if np.any(pts[:, 2] < 0.05):
                        continue
                    uv = np.stack([info.fx * pts[:, 0] / pts[:, 2] + info.cx, info.fy * pts[:, 1] / pts[:, 2] + info.cy], 1)
                    mask = (seg_s >= 0) & (body_ids == body)
                    idx = len(objs)
                    seg_out[mask] = idx
                    in_frame = (uv[:, 0] >= 0) & (uv[:, 0] <= cfg.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cfg.height - 1)
                    hull = cv2.convexHull(uv.astype(np.float32))
                    objs.append({
                        "class": spec.cls, "class_index": int(ci),
                        "keypoints_px": uv.round(3).tolist(),
                        "location": T_cam_obj[:3, 3].round(5).tolist(),
                        "quaternion_xyzw": Rotation.from_matrix(T_cam_obj[:3, :3]).as_quat().round(6).tolist(),
                        "pixels_visible": int(mask.sum()),
                        "hull_area_px": float(cv2.contourArea(hull)),
                        "in_frame": in_frame.tolist(),
                    })
                rgbs.append(rgb_s)
                depths.append(np.clip(np.rint(depth_s * 1000.0), 0, 65535).astype(np.uint16))
                segs.append(seg_out)
                annos.append({"light": light, "objects": objs})
        finally:
            p.disconnect(world.client)
    _atomic_save_npz(npz_path, rgb=np.stack(rgbs), depth_mm=np.stack(depths), seg=np.stack(segs))
    meta = {"seed": cfg.seed, "shard": shard, "width": cfg.width, "height": cfg.height,
            "K": info.K.tolist(), "classes": list(cfg.classes), "images": annos}
    _atomic_save_json(json_path, meta)
    return npz_path


def _worker(args):
    cfg, shard = args
    return str(generate_shard(cfg, shard))


def generate(cfg: DatagenConfig, progress: bool = True) -> list[Path]:
    """Render ``cfg.n_images`` images in shards with ``cfg.workers`` processes and (``progress``) a
    progress bar."""
    from multiprocessing import get_context

    from tqdm import tqdm

    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_shards = (cfg.n_images + cfg.shard_size - 1) // cfg.shard_size
    jobs = [(cfg, s) for s in range(n_shards)]
    paths = []
    if cfg.workers <= 1:
        for j in tqdm(jobs, desc="datagen shards", unit="shard", disable=not progress):
            paths.append(Path(_worker(j)))
    else:
        with get_context("spawn").Pool(cfg.workers) as pool:
            for path in tqdm(pool.imap_unordered(_worker, jobs), total=len(jobs), desc="datagen shards", unit="shard",
                             disable=not progress):
                paths.append(Path(path))
    return sorted(paths)
