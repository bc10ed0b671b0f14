"""Dead reckoning with the gyro's heading (stack.dead_reckoning) and the simulated gyro (sim.imu)."""
import math

import numpy as np
import pytest

from sim.imu import NOISE_DENSITY, Gyro
from stack.dead_reckoning import DeadReckoning
from stack.transforms import yaw_of


def test_gyro_bias_is_what_a_one_second_calibration_leaves():
    biases = np.array([Gyro(np.random.default_rng(s), calibration_s=1.0).bias for s in range(400)])
    assert abs(biases.mean()) < 3 * NOISE_DENSITY / math.sqrt(400)
    assert 0.8 * NOISE_DENSITY < biases.std() < 1.2 * NOISE_DENSITY
    longer = np.array([Gyro(np.random.default_rng(s), calibration_s=16.0).bias for s in range(400)])
    assert longer.std() == pytest.approx(biases.std() / 4, rel=0.2)
    with pytest.raises(ValueError, match="calibration_s"):
        Gyro(np.random.default_rng(0), calibration_s=0)


def test_dead_reckoning_closes_a_square_that_the_wheels_over_turn():
    """A 2 m square at 240 Hz: the wheels' travel is right, their heading counts each 90 deg turn as
    135 deg (a skid-steer base slipping); with the gyro's heading the square closes."""
    dt, gyro = 1 / 240, Gyro(np.random.default_rng(1))
    with_gyro, wheels_only = DeadReckoning(), DeadReckoning()
    for _ in range(4):
        for _ in range(480):  # 2 m straight at 1 m/s
            with_gyro.step(dt, 0.0, gyro.measure(0.0, dt) * dt)
            wheels_only.step(dt, 0.0, 0.0)
        for _ in range(240):  # 90 deg in 1 s, turning in place
            rate = math.pi / 2
            with_gyro.step(0.0, 0.0, gyro.measure(rate, dt) * dt)
            wheels_only.step(0.0, 0.0, 1.5 * rate * dt)
    assert np.linalg.norm(with_gyro.T[:2, 3]) < 0.02
    assert abs(yaw_of(with_gyro.T)) < math.radians(0.5)
    assert np.linalg.norm(wheels_only.T[:2, 3]) > 1.0  # what the wheel odometry alone gives


def test_dead_reckoning_step_is_in_the_base_frame():
    dr = DeadReckoning()
    dr.step(0.0, 0.0, math.pi / 2)
    T = dr.step(1.0, 0.5, 0.0)  # facing +y: forward is +y, left is -x
    np.testing.assert_allclose(T[:2, 3], [-0.5, 1.0], atol=1e-12)
    assert yaw_of(T) == pytest.approx(math.pi / 2)
