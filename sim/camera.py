"""The RealSense D435i: colour + depth aligned to colour, rendered by PyBullet, with the D435i's noise.

Depth noise (DESIGN.md): sigma_z = z^2 * subpixel / (f_ir * baseline); holes in the stereo shadow
beside depth edges (the part of the background one IR camera cannot see) and at range limits.
Darkness: the colour sensor has an IR-cut filter, so at light 0 the image is read noise only, while
the depth (active 850 nm projector) is unchanged.

The rendering machinery (clients, GL matrices, the noise-free render, the second-process worker) is
``sim.render``; its names stay importable from here.
"""
from __future__ import annotations

import logging
try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11: the same parser, backported
    import tomli as tomllib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import pybullet as p

from sim.render import FAR, NEAR, RenderWorker, gl_matrices, new_client, render_raw  # noqa: F401 (re-exported)
from stack.messages import CameraInfo

log = logging.getLogger(__name__)
HARDWARE_TOML = Path(__file__).parent / "data" / "hardware.toml"


@lru_cache(maxsize=1)
def hardware() -> dict:
    """The figures of ``sim/data/hardware.toml`` as a dict, checked by the typed spec
    (``sim.sensors.hardware_spec``, which the sensor models here read) first."""
    from sim.sensors import hardware_spec

    hardware_spec()  # a missing, unknown or mistyped figure fails here, named
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
        from sim.sensors import hardware_spec

        h = hardware_spec().d435i
        return DepthNoise(h.depth_fx, h.baseline, h.subpixel, h.depth_min, h.depth_max)

    def sigma(self, z: np.ndarray) -> np.ndarray:
        return z * z * self.subpixel / (self.depth_fx * self.baseline)


def default_camera_info(width: int | None = None, height: int | None = None) -> CameraInfo:
    from sim.sensors import hardware_spec

    h = hardware_spec().d435i
    info = CameraInfo.from_fov(h.width, h.height, h.fx, h.fy)
    if width and height and (width, height) != (info.width, info.height):
        info = info.scaled(width, height)
    return info


def project(points_cam: np.ndarray, info: CameraInfo) -> np.ndarray:
    """Pinhole projection of (N, 3) optical-frame points to (N, 2) pixels."""
    z = points_cam[:, 2:3]
    return np.hstack([info.fx * points_cam[:, :1] / z + info.cx, info.fy * points_cam[:, 1:2] / z + info.cy])


@lru_cache(maxsize=1)
def _gauss_table() -> np.ndarray:
    """The standard normal's 65536 equiprobable quantiles (float32): a 16-bit inverse-CDF sampler."""
    from scipy.special import ndtri

    return ndtri((np.arange(65536) + 0.5) / 65536).astype(np.float32)


def standard_normal(rng: np.random.Generator, shape) -> np.ndarray:
    """Standard normal float32 samples, ~3x cheaper than ``rng.standard_normal``: 16 random bits per
    sample looked up in the normal's quantile table (tails cut at 4.3 sigma; variance 0.99998)."""
    n = int(np.prod(shape))
    bits = rng.bit_generator.random_raw((n + 3) // 4).view(np.uint16)[:n]
    return np.take(_gauss_table(), bits).reshape(shape)


def stereo_shadow(depth_m: np.ndarray, fb: float) -> np.ndarray:
    """Pixels that the second imager (offset along +x) cannot see: a nearer surface to their right whose
    disparity exceeds theirs by more than its distance in pixels hides them (``fb`` = f_px * baseline).

    disp[k] - disp[j] > k - j  <=>  disp[k] - k > disp[j] - j, so one running maximum from the right
    per row finds every such pixel, however wide the shadow.
    """
    H, W = depth_m.shape
    valid = depth_m > 0
    g = np.where(valid, np.float32(fb) / np.maximum(depth_m, np.float32(1e-3)), np.float32(0.0))
    g -= np.arange(W, dtype=np.float32)
    right_max = np.maximum.accumulate(g[:, ::-1], axis=1)[:, ::-1]  # max over k >= j
    shadow = np.zeros((H, W), dtype=bool)
    np.greater(right_max[:, 1:], g[:, :-1], out=shadow[:, :-1])  # max over k > j
    return shadow & valid


def apply_depth_noise(depth_m: np.ndarray, info: CameraInfo, model: DepthNoise, rng: np.random.Generator) -> np.ndarray:
    z = depth_m.astype(np.float32)  # a copy
    # stereo shadow: the part of the background beside a depth edge that one IR imager cannot see
    # (projector/imager offset along +x, so to the right of nearer surfaces here)
    bad = stereo_shadow(z, info.fx * model.baseline)
    noise = standard_normal(rng, z.shape)
    noise *= z
    noise *= z
    noise *= np.float32(model.subpixel / (model.depth_fx * model.baseline))  # sigma_z = z^2 * subpixel / (f b)
    z += noise
    # random dropouts: a binomial count of pixels at uniformly drawn positions
    k = rng.binomial(z.size, model.dropout)
    bad.reshape(-1)[rng.integers(0, z.size, k)] = True
    bad |= (z < model.depth_min) | (z > model.depth_max)
    z[bad] = 0.0
    return z


_COLOR_NOISE_BITS = 12


@lru_cache(maxsize=4)
def _color_noise_table(read_noise: float) -> np.ndarray:
    """(256 * 4096,) uint8: the noisy output for each (signal DN, noise quantile) pair, flattened."""
    from scipy.special import ndtri

    n = 1 << _COLOR_NOISE_BITS
    q = ndtri((np.arange(n) + 0.5) / n)[None, :]  # equiprobable standard normal quantiles (tails 3.5 sigma)
    v = np.arange(256, dtype=float)[:, None]
    sigma = np.sqrt(read_noise * read_noise + v / 50.0)  # read noise and shot noise
    return np.clip(np.rint(v + sigma * q), 0, 255).astype(np.uint8).reshape(-1)


def apply_color_noise(rgb: np.ndarray, light: float, read_noise: float, rng: np.random.Generator | None) -> np.ndarray:
    """Scene light level scales the exposure (no auto-exposure beyond the lit level); read noise and shot
    noise on top. Both are Gaussian, so one draw with their combined sigma sqrt(read^2 + signal / 50),
    made by table: each pixel's signal and 12 random bits pick the noisy value."""
    img = np.asarray(rgb, dtype=np.uint8)
    if light != 1.0:
        scale = np.clip(np.rint(np.arange(256) * float(light)), 0, 255).astype(np.uint8)
        img = np.take(scale, img)
    if rng is None or read_noise <= 0:
        return img.copy() if img is rgb else img
    n = img.size
    bits = rng.bit_generator.random_raw((n + 3) // 4).view(np.uint16)[:n]
    idx = img.reshape(-1).astype(np.uint32) << _COLOR_NOISE_BITS
    idx |= bits >> (16 - _COLOR_NOISE_BITS)
    return np.take(_color_noise_table(float(read_noise)), idx).reshape(img.shape)


def render_rgbd(client: int, T_world_cam: np.ndarray, info: CameraInfo, light: float = 1.0,
                rng: np.random.Generator | None = None, noise: bool = True, renderer: int = p.ER_TINY_RENDERER,
                light_direction=(0.3, 0.4, 1.0), segmentation: bool = True):
    """(rgb, depth_m, segmentation) as the D435i would give them (noise when ``noise`` and an rng);
    segmentation None when ``segmentation=False`` (colour and depth the same either way)."""
    rgb, depth, seg = render_raw(client, T_world_cam, info, renderer, light_direction, segmentation=segmentation)
    if noise and rng is not None:
        model = DepthNoise.from_hardware()
        depth = apply_depth_noise(depth, info, model, rng)
        rgb = apply_color_noise(rgb, light, hardware()["d435i"]["read_noise"], rng)
    else:
        rgb = apply_color_noise(rgb, light, 0.0, None)
        h = hardware()["d435i"]
        depth = np.where((depth >= h["depth_min"]) & (depth <= h["depth_max"]), depth, 0.0).astype(np.float32)
    # the D435i reports depth in whole millimetres (16UC1): round as it does, so a bag round trip is exact
    depth = (np.rint(depth * 1000.0) / 1000.0).astype(np.float32)
    return rgb, depth, seg
