"""The RealSense D435i: colour + depth aligned to colour, rendered by PyBullet, with the D435i's noise.

Depth noise (DESIGN.md): sigma_z = z^2 * subpixel / (f_ir * baseline); holes in the stereo shadow
beside depth edges (the part of the background one IR camera cannot see) and at range limits.
Darkness: the colour sensor has an IR-cut filter, so at light 0 the image is read noise only, while
the depth (active 850 nm projector) is unchanged.
"""
from __future__ import annotations

import logging
import pkgutil
import tomllib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import pybullet as p

from stack.messages import CameraInfo

log = logging.getLogger(__name__)
HARDWARE_TOML = Path(__file__).parent / "data" / "hardware.toml"
NEAR, FAR = 0.05, 30.0


@lru_cache(maxsize=1)
def hardware() -> dict:
    with open(HARDWARE_TOML, "rb") as f:
        return tomllib.load(f)


@dataclass
class DepthNoise:
    depth_fx: float = 384.0
    baseline: float = 0.05
    subpixel: float = 0.08
    depth_min: float = 0.28
    depth_max: float = 10.0
    dropout: float = 0.003  # random invalid pixels

    @staticmethod
    def from_hardware() -> "DepthNoise":
        h = hardware()["d435i"]
        return DepthNoise(h["depth_fx"], h["baseline"], h["subpixel"], h["depth_min"], h["depth_max"])

    def sigma(self, z: np.ndarray) -> np.ndarray:
        return z * z * self.subpixel / (self.depth_fx * self.baseline)


def default_camera_info(width: int | None = None, height: int | None = None) -> CameraInfo:
    h = hardware()["d435i"]
    info = CameraInfo.from_fov(h["width"], h["height"], h["fx"], h["fy"])
    if width and height and (width, height) != (info.width, info.height):
        info = info.scaled(width, height)
    return info


def new_client(renderer: str = "auto") -> tuple[int, int]:
    """A DIRECT PyBullet client and the renderer flag to use: EGL (Mesa llvmpipe) when it loads, else TinyRenderer."""
    client = p.connect(p.DIRECT)
    flag = p.ER_TINY_RENDERER
    if renderer in ("auto", "egl"):
        loader = pkgutil.get_loader("eglRenderer")
        plugin = -1
        if loader is not None:
            plugin = p.loadPlugin(loader.get_filename(), "_eglRendererPlugin", physicsClientId=client)
        if plugin >= 0:
            flag = p.ER_BULLET_HARDWARE_OPENGL
        elif renderer == "egl":
            raise RuntimeError("EGL renderer requested but the eglRenderer plugin did not load")
        else:
            log.info("EGL renderer unavailable; using TinyRenderer")
    return client, flag


def gl_matrices(T_world_cam: np.ndarray, info: CameraInfo, near: float = NEAR, far: float = FAR):
    """PyBullet view and projection matrices (column-major lists) for an optical-frame camera pose."""
    T_world_gl = T_world_cam @ np.diag([1.0, -1.0, -1.0, 1.0])  # optical (z fwd, y down) -> GL (z back, y up)
    view = np.linalg.inv(T_world_gl)
    W, H = info.width, info.height
    fx, fy, cx, cy = info.fx, info.fy, info.cx + 0.5, info.cy + 0.5  # pixel index -> continuous coordinate
    proj = np.array([
        [2 * fx / W, 0, 1 - 2 * cx / W, 0],
        [0, 2 * fy / H, 2 * cy / H - 1, 0],
        [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, -1, 0],
    ])
    return view.T.reshape(-1).tolist(), proj.T.reshape(-1).tolist()


def project(points_cam: np.ndarray, info: CameraInfo) -> np.ndarray:
    """Pinhole projection of (N, 3) optical-frame points to (N, 2) pixels."""
    z = points_cam[:, 2:3]
    return np.hstack([info.fx * points_cam[:, :1] / z + info.cx, info.fy * points_cam[:, 1:2] / z + info.cy])


def render_raw(client: int, T_world_cam: np.ndarray, info: CameraInfo, renderer: int = p.ER_TINY_RENDERER,
               light_direction=(0.3, 0.4, 1.0), shadow: bool = False):
    """Noise-free (rgb uint8 HxWx3, depth_m float32 HxW, segmentation int32 HxW)."""
    view, proj = gl_matrices(T_world_cam, info)
    _, _, rgba, zbuf, seg = p.getCameraImage(
        info.width, info.height, view, proj, renderer=renderer, lightDirection=list(light_direction),
        shadow=int(shadow), physicsClientId=client)
    rgb = np.asarray(rgba, dtype=np.uint8).reshape(info.height, info.width, 4)[..., :3]
    zbuf = np.asarray(zbuf, dtype=np.float64).reshape(info.height, info.width)
    # depth buffer -> distance along the optical axis
    depth = (FAR * NEAR / (FAR - (FAR - NEAR) * zbuf)).astype(np.float32)
    depth[zbuf >= 1.0] = 0.0
    segm = np.asarray(seg, dtype=np.int32).reshape(info.height, info.width)
    return rgb, depth, segm


def apply_depth_noise(depth_m: np.ndarray, info: CameraInfo, model: DepthNoise, rng: np.random.Generator) -> np.ndarray:
    z = depth_m.astype(np.float32).copy()
    valid = z > 0
    # stereo shadow: a background pixel is invisible to the second imager when a nearer surface within
    # its disparity difference lies beside it (to its right here: projector/imager offset along +x)
    fb = info.fx * model.baseline
    disp = np.where(valid, fb / np.maximum(z, 1e-3), 0.0)
    shadow = np.zeros_like(valid)
    max_shift = int(min(32, np.ceil(fb / model.depth_min - fb / model.depth_max)))
    for s in range(1, max_shift + 1):
        nearer = np.zeros_like(disp)
        nearer[:, :-s] = disp[:, s:]
        shadow |= (nearer - disp) > s
    z += rng.standard_normal(z.shape).astype(np.float32) * model.sigma(z).astype(np.float32)
    bad = shadow | (rng.random(z.shape) < model.dropout) | (z < model.depth_min) | (z > model.depth_max) | ~valid
    z[bad] = 0.0
    return z


def apply_color_noise(rgb: np.ndarray, light: float, read_noise: float, rng: np.random.Generator | None) -> np.ndarray:
    """Scene light level scales the exposure (no auto-exposure beyond the lit level); read noise on top."""
    img = rgb.astype(np.float32) * float(light)
    if rng is not None and read_noise > 0:
        img += rng.standard_normal(img.shape).astype(np.float32) * read_noise
        img += rng.standard_normal(img.shape).astype(np.float32) * np.sqrt(np.maximum(img, 0) / 50.0)  # shot noise
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_rgbd(client: int, T_world_cam: np.ndarray, info: CameraInfo, light: float = 1.0,
                rng: np.random.Generator | None = None, noise: bool = True, renderer: int = p.ER_TINY_RENDERER,
                light_direction=(0.3, 0.4, 1.0)):
    """(rgb, depth_m, segmentation) as the D435i would give them (noise when ``noise`` and an rng)."""
    rgb, depth, seg = render_raw(client, T_world_cam, info, renderer, light_direction)
    if noise and rng is not None:
        model = DepthNoise.from_hardware()
        depth = apply_depth_noise(depth, info, model, rng)
        rgb = apply_color_noise(rgb, light, hardware()["d435i"]["read_noise"], rng)
    else:
        rgb = apply_color_noise(rgb, light, 0.0, None)
        h = hardware()["d435i"]
        depth = np.where((depth >= h["depth_min"]) & (depth <= h["depth_max"]), depth, 0.0).astype(np.float32)
    return rgb, depth, seg
