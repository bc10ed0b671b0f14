"""Which camera images the detector runs on when the robot barely moves between them.

A robot standing still sees the same view at the camera's full rate; running the network on every
one of those images costs the most CPU of the whole stack and adds little: the same objects, from
the same viewpoint. :class:`KeyframeGate` passes an image to the detector only when the robot has
moved or turned enough since the last image it passed, by its wheel odometry (the cheapest pose a
robot has, and one that is known before the image is processed), or when enough time has gone by,
so a still robot still looks every so often (objects can be moved in front of it).

The decision depends only on the messages seen before the image, in stream order, so two gates fed
the same stream pass the same images, whichever thread or process consults them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stack.messages import CameraFrame, WheelOdometry


STAMP_TOLERANCE_S = 1e-6


@dataclass(frozen=True)
class KeyframeSettings:
    """``min_motion_m`` / ``min_turn_deg``: the base's travel and turn since the last passed image that
    pass the next one (0: that test is off; both 0: the gate is off and every image passes);
    ``max_interval_s``: an image this long after the last passed one passes anyway (0: never)."""

    min_motion_m: float = 0.0
    min_turn_deg: float = 0.0
    max_interval_s: float = 1.0

    @property
    def enabled(self) -> bool:
        return self.min_motion_m > 0 or self.min_turn_deg > 0


def keyframe_gate(settings: KeyframeSettings | None) -> "KeyframeGate | None":
    """A gate for ``settings``, or None when there are none or they are off (every image passes)."""
    return KeyframeGate(settings) if settings is not None and settings.enabled else None


class KeyframeGate:
    """Feed it the wheel odometry (``on_wheel_odometry``) and ask, per image, ``passes(frame)``.

    Without wheel odometry (a bag without ``/odom``) the motion is unknown and every image passes."""

    def __init__(self, settings: KeyframeSettings):
        self.settings = settings
        self._T_odom_base: np.ndarray | None = None
        self._last: tuple[float, np.ndarray | None] | None = None  # stamp and odometry pose of the last passed image
        self.passed = 0
        self.held = 0  # images the gate kept from the detector

    def on_wheel_odometry(self, msg: WheelOdometry) -> None:
        self._T_odom_base = np.asarray(msg.T_odom_base, dtype=float)

    def mark(self, frame: CameraFrame) -> None:
        """Count ``frame`` as passed (its detections came from elsewhere)."""
        self._last = (float(frame.stamp), None if self._T_odom_base is None else self._T_odom_base.copy())
        self.passed += 1

    def passes(self, frame: CameraFrame) -> bool:
        """Whether the detector should run on ``frame``; a passed frame becomes the new reference."""
        s = self.settings
        if not s.enabled or self._last is None or self._T_odom_base is None or self._last[1] is None:
            self.mark(frame)
            return True
        stamp, T_ref = self._last
        # within a microsecond: stamps read back from a bag's nanoseconds are not the live floats
        go = s.max_interval_s > 0 and float(frame.stamp) - stamp >= s.max_interval_s - STAMP_TOLERANCE_S
        if not go:
            rel = np.linalg.solve(T_ref, self._T_odom_base)
            if s.min_motion_m > 0 and float(np.linalg.norm(rel[:3, 3])) >= s.min_motion_m:
                go = True
            elif s.min_turn_deg > 0:
                cos = (float(np.trace(rel[:3, :3])) - 1.0) / 2.0
                go = math.degrees(math.acos(min(1.0, max(-1.0, cos)))) >= s.min_turn_deg
        if go:
            self.mark(frame)
        else:
            self.held += 1
        return go
