"""Sensor faults as seeded transforms of the message stream, between the sensors and whoever listens
(the stack, a bag recorder): what a flaky driver, a loaded computer or a slipping wheel publishes.

In a scenario file (``[faults]``) or as ``--fault NAME=VALUE`` on ``dopeslam run`` / ``record``:

=================== ======= ============================================================================
name                value   effect on the stream
=================== ======= ============================================================================
lidar_drop          0-1     each LiDAR sweep is dropped with this probability
partial_sweep       0-1     each sweep, with this probability, loses a random 30-70 % wedge of azimuth
camera_drop         0-1     each camera frame is dropped with this probability
camera_latency      s       frames arrive this much later, stamped with their true capture time
camera_late_stamp   s       frames arrive this much later and are stamped on arrival (wrong stamps)
camera_clock_offset s       frames are stamped this much off (the camera's clock against the LiDAR's)
depth_holes         0-1     this fraction of the depth image is invalid (0), in blobs
motion_blur         s       exposure time: colour smeared along the image motion over this time
exposure            gain    colour brightness multiplied by this (0.5 underexposed, 2 overexposed)
flicker             0-1     each frame's brightness is multiplied by 1 +- up to this (light flicker)
wheel_slip          0-1     wheel odometry's travelled distance over-reported by up to this fraction
=================== ======= ============================================================================

All randomness comes from one generator seeded from the episode's seed (``fault_seed``), so a
faulty episode is as repeatable as a clean one. Ground truth carried in a message (``T_world_*``) is
left true.
"""
from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Iterator
from dataclasses import replace

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from stack.errors import DopeSlamError
from stack.messages import CameraFrame, LidarScan, WheelOdometry
from stack.transforms import inv

FAULT_SEED_KEY = 0xFA17  # mixed with the episode seed: faults draw from their own stream


class Faults(BaseModel):
    model_config = ConfigDict(extra="forbid")

    lidar_drop: float = Field(0.0, ge=0.0, le=1.0)
    partial_sweep: float = Field(0.0, ge=0.0, le=1.0)
    camera_drop: float = Field(0.0, ge=0.0, le=1.0)
    camera_latency: float = Field(0.0, ge=0.0, le=5.0)
    camera_late_stamp: float = Field(0.0, ge=0.0, le=5.0)
    camera_clock_offset: float = Field(0.0, ge=-5.0, le=5.0)
    depth_holes: float = Field(0.0, ge=0.0, le=1.0)
    motion_blur: float = Field(0.0, ge=0.0, le=0.5)
    exposure: float = Field(1.0, gt=0.0, le=10.0)
    flicker: float = Field(0.0, ge=0.0, le=1.0)
    wheel_slip: float = Field(0.0, ge=0.0, le=1.0)

    @property
    def active(self) -> dict:
        """The faults set away from their no-fault value."""
        clean = Faults()
        return {k: v for k, v in self.model_dump().items() if v != getattr(clean, k)}


class FaultError(DopeSlamError, ValueError):
    """A ``--fault NAME=VALUE`` that cannot be used (names the fault and what was expected)."""


def parse_overrides(items: Iterable[str], base: Faults | None = None) -> Faults:
    """``["lidar_drop=0.2", ...]`` over ``base``; FaultError names the bad item."""
    values = (base or Faults()).model_dump()
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in Faults.model_fields:
            raise FaultError(f"fault {item!r}: expected NAME=VALUE with NAME one of {sorted(Faults.model_fields)}")
        try:
            values[name] = float(value)
        except ValueError:
            raise FaultError(f"fault {name}: expected a number, got {value!r}") from None
    try:
        return Faults(**values)
    except ValidationError as e:
        err = e.errors()[0]
        raise FaultError(f"fault {err['loc'][0]}: {err['msg']}") from None


def fault_seed(episode_seed: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([int(episode_seed), FAULT_SEED_KEY])


class FaultInjector:
    """``apply(messages)``: the stream as the faulty drivers publish it, in arrival order.

    ``counts``: how many messages of each kind came in, were dropped, were cut short.
    """

    def __init__(self, faults: Faults, seed: int):
        self.f = faults
        self.rng = np.random.default_rng(fault_seed(seed))
        self.counts = {"scans": 0, "scans_dropped": 0, "scans_partial": 0, "images": 0, "images_dropped": 0,
                       "wheel": 0}
        self._prev_cam: tuple[float, np.ndarray] | None = None
        self._odom_prev: np.ndarray | None = None
        self._odom_out: np.ndarray | None = None

    @property
    def delay(self) -> float:
        return self.f.camera_latency + self.f.camera_late_stamp

    def apply(self, messages: Iterable) -> Iterator:
        """Messages in, messages out, ordered by arrival time (stamp, plus latency for images)."""
        queue: list = []  # (arrival, seq, msg): delayed images wait here
        seq = 0
        clock = -math.inf
        for msg in messages:
            out = self.transform(msg)
            now = msg.stamp
            if isinstance(msg, LidarScan) and len(msg.times_s):
                now = msg.stamp + float(np.max(msg.times_s))  # a sweep is published once it ends
            clock = max(clock, now)
            while queue and queue[0][0] <= clock:
                yield heapq.heappop(queue)[2]
            if out is None:
                continue
            if isinstance(out, CameraFrame) and self.delay > 0:
                heapq.heappush(queue, (msg.stamp + self.delay, seq, out))
                seq += 1
                continue
            yield out
        while queue:
            yield heapq.heappop(queue)[2]

    def transform(self, msg):
        """One message as published (None: dropped). Draws from the generator in a fixed order."""
        if isinstance(msg, LidarScan):
            return self._scan(msg)
        if isinstance(msg, CameraFrame):
            return self._image(msg)
        if isinstance(msg, WheelOdometry):
            return self._wheel(msg)
        return msg

    # --- LiDAR ---
    def _scan(self, scan: LidarScan) -> LidarScan | None:
        self.counts["scans"] += 1
        u_drop, u_part, cut, start = self.rng.random(4)
        if u_drop < self.f.lidar_drop:
            self.counts["scans_dropped"] += 1
            return None
        if u_part < self.f.partial_sweep:
            self.counts["scans_partial"] += 1
            az = np.arctan2(scan.points[:, 1], scan.points[:, 0])
            width = 2 * math.pi * (0.3 + 0.4 * cut)
            lo = -math.pi + 2 * math.pi * start
            keep = ((az - lo) % (2 * math.pi)) > width
            return replace(scan, points=scan.points[keep], times_s=scan.times_s[keep],
                           ring=None if scan.ring is None else scan.ring[keep],
                           intensity=None if scan.intensity is None else scan.intensity[keep])
        return scan

    # --- camera ---
    def _image(self, frame: CameraFrame) -> CameraFrame | None:
        self.counts["images"] += 1
        f = self.f
        u_drop, u_flicker = self.rng.random(2)
        hole_seed = int(self.rng.integers(2**63))
        prev, self._prev_cam = self._prev_cam, (frame.stamp, frame.T_world_camera)
        if u_drop < f.camera_drop:
            self.counts["images_dropped"] += 1
            return None
        rgb, depth = frame.rgb, frame.depth_m
        gain = f.exposure * (1.0 + f.flicker * (2.0 * u_flicker - 1.0))
        if rgb is not None and f.motion_blur > 0 and prev is not None and frame.T_world_camera is not None:
            rgb = _motion_blur(rgb, frame, prev, f.motion_blur)
        if rgb is not None and gain != 1.0:
            rgb = np.clip(rgb.astype(np.float32) * gain, 0, 255).astype(np.uint8)
        if depth is not None and f.depth_holes > 0:
            depth = np.where(_hole_mask(depth.shape, f.depth_holes, np.random.default_rng(hole_seed)), 0.0,
                             depth).astype(np.float32)
        stamp = frame.stamp + f.camera_clock_offset + f.camera_late_stamp
        if rgb is frame.rgb and depth is frame.depth_m and stamp == frame.stamp:
            return frame
        return replace(frame, stamp=stamp, rgb=rgb, depth_m=depth, extra=dict(frame.extra))

    # --- wheels ---
    def _wheel(self, msg: WheelOdometry) -> WheelOdometry:
        self.counts["wheel"] += 1
        u = self.rng.random()
        if self.f.wheel_slip <= 0:
            return msg
        scale = 1.0 + self.f.wheel_slip * u  # the wheels turn further than the robot goes
        if self._odom_prev is None:
            self._odom_prev, self._odom_out = msg.T_odom_base.copy(), msg.T_odom_base.copy()
            return msg
        step = inv(self._odom_prev) @ msg.T_odom_base
        step[:3, 3] *= scale
        self._odom_prev = msg.T_odom_base.copy()
        self._odom_out = self._odom_out @ step
        return WheelOdometry(msg.stamp, self._odom_out.copy(), msg.v * scale, msg.w)


def _hole_mask(shape, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """A boolean mask covering about ``fraction`` of the image in blobs (as stereo matching fails)."""
    h, w = shape
    coarse = rng.random((max(1, h // 16), max(1, w // 16))).astype(np.float32)
    field = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    if fraction >= 1.0:
        return np.ones(shape, dtype=bool)
    return field < np.quantile(field, fraction)


def _motion_blur(rgb: np.ndarray, frame: CameraFrame, prev: tuple[float, np.ndarray], exposure: float) -> np.ndarray:
    """Colour smeared along the image motion at the centre over ``exposure`` seconds (from the camera's
    own motion between this frame and the last one)."""
    t0, T0 = prev
    dt = frame.stamp - t0
    if T0 is None or dt <= 0:
        return rgb
    rel = inv(T0) @ frame.T_world_camera  # camera motion in the earlier camera's frame
    rotvec = cv2.Rodrigues(rel[:3, :3])[0].ravel()
    # pixel velocity at the centre from rotation (dominant) and sideways translation at 1.5 m
    vx = (frame.info.fx * (rotvec[1] + rel[0, 3] / 1.5)) / dt
    vy = (frame.info.fy * (-rotvec[0] + rel[1, 3] / 1.5)) / dt
    length = math.hypot(vx, vy) * exposure
    if length < 1.0:
        return rgb
    n = int(min(61, math.ceil(length))) | 1
    kernel = np.zeros((n, n), np.float32)
    c = n // 2
    ang = math.atan2(vy, vx)
    for k in range(n):
        s = k - c
        kernel[int(round(c + s * math.sin(ang))), int(round(c + s * math.cos(ang)))] = 1.0
    kernel /= kernel.sum()
    return cv2.filter2D(rgb, -1, kernel)
