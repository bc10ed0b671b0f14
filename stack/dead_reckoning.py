"""Dead reckoning of a skid-steer base: the wheels' travel with the gyro's heading (the wheel
odometry's own heading over-counts turns, the wheels slipping sideways; the gyro's does not)."""
from __future__ import annotations

import math

import numpy as np

from stack.transforms import inv


class DeadReckoning:
    """The pose from the wheels' travel and the gyro's heading (wheel odometry over-counts turns on a
    skid-steer base; the gyro does not): integrated in the odometry frame."""

    def __init__(self, T0: np.ndarray | None = None):
        self.T = np.eye(4) if T0 is None else np.array(T0, dtype=float)

    def step(self, forward_m: float, lateral_m: float, dyaw: float) -> np.ndarray:
        """Advance by a travel (base frame, metres) over which the heading changed by ``dyaw``."""
        yaw = math.atan2(self.T[1, 0], self.T[0, 0])
        mid = yaw + 0.5 * dyaw
        c, s = math.cos(mid), math.sin(mid)
        self.T[0, 3] += c * forward_m - s * lateral_m
        self.T[1, 3] += s * forward_m + c * lateral_m
        y = yaw + dyaw
        self.T[:2, :2] = [[math.cos(y), -math.sin(y)], [math.sin(y), math.cos(y)]]
        return self.T.copy()

    def step_wheels(self, T_wheels_prev: np.ndarray, T_wheels: np.ndarray, dyaw: float) -> np.ndarray:
        """Advance by the wheel odometry's travel between two of its poses (4x4, its own frame), over
        which the gyro turned by ``dyaw``."""
        step = inv(T_wheels_prev) @ T_wheels
        return self.step(float(step[0, 3]), float(step[1, 3]), dyaw)
