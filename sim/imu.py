"""The yaw-rate gyro of the robot's IMU (the Jackal's, or the D435i's Bosch BMI055: noise density
0.014 deg/s/sqrt(Hz), zero-rate offset up to +-1 deg/s before calibration; the figures are
``sim/data/hardware.toml``'s ``[gyro]``, typed in ``sim.sensors``).

The gyro measures the base's true yaw rate (the simulator's) plus a bias and white noise. The bias
is what a stationary calibration at power-up leaves (the robot stands before each episode): the
zero-rate offset averaged over ``calibration_s`` seconds of noisy readings, so its residual is the
noise's mean over that time; in use it then walks slowly (in-run bias instability). The jackal's
own odometry (robot_localization's EKF) fuses this yaw rate with the wheels' travel, as
``stack.dead_reckoning.DeadReckoning`` does."""
from __future__ import annotations

import math

import numpy as np

from sim.sensors import hardware_spec

_SPEC = hardware_spec().gyro  # sim/data/hardware.toml [gyro]
NOISE_DENSITY = math.radians(_SPEC.noise_density_deg_s_rthz)  # rad/s/sqrt(Hz)
ZERO_RATE_OFFSET = math.radians(_SPEC.zero_rate_offset_deg_s)  # rad/s, 1-sigma before calibration
BIAS_WALK = math.radians(_SPEC.bias_walk_deg_s_rts)  # rad/s/sqrt(s)


class Gyro:
    """z-axis gyro readings (rad/s) from the true yaw rate, seeded."""

    def __init__(self, rng: np.random.Generator, calibration_s: float | None = None):
        calibration_s = _SPEC.calibration_s if calibration_s is None else calibration_s
        if calibration_s <= 0:
            raise ValueError(f"calibration_s: expected a positive duration, got {calibration_s}")
        self.rng = rng
        offset = ZERO_RATE_OFFSET * float(rng.standard_normal())
        # the calibration's estimate of the offset is off by the noise's mean over its duration
        estimate = offset + NOISE_DENSITY / math.sqrt(calibration_s) * float(rng.standard_normal())
        self.bias = offset - estimate

    def measure(self, true_rate: float, dt: float) -> float:
        """One reading over a sample period ``dt`` (s): the mean rate plus bias and noise."""
        if dt <= 0:
            raise ValueError(f"dt: expected a positive sample period, got {dt}")
        self.bias += BIAS_WALK * math.sqrt(dt) * float(self.rng.standard_normal())
        return true_rate + self.bias + NOISE_DENSITY / math.sqrt(dt) * float(self.rng.standard_normal())
