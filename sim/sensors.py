"""The simulated robot's hardware, as a user reads and changes it: one typed spec (pydantic) of every
figure in ``sim/data/hardware.toml`` (the Jackal base, the D435i camera, the 32-beam Velodyne, the
IMU's yaw-rate gyro), checked when it is read: a missing, unknown or mistyped figure is one line
naming the section and field.

    from sim.sensors import hardware_spec
    spec = hardware_spec()
    spec.d435i.fx, spec.velodyne.range_noise, spec.gyro.noise_density_deg_s_rthz

Edit ``sim/data/hardware.toml`` (or point ``load_hardware`` at a copy) to simulate other hardware.
The sensor models read their figures here: the camera's noise and intrinsics (``sim.camera``), the
LiDAR's beam pattern (``sim.lidar.BeamPattern``) and the gyro (``sim.imu.Gyro``).
"""
from __future__ import annotations

import functools
import os
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

HARDWARE_TOML = Path(__file__).parent / "data" / "hardware.toml"


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class JackalSpec(_Spec):
    """The Clearpath Jackal base (metres, kilograms, seconds)."""
    chassis_size: tuple[float, float, float]
    chassis_mass: float = Field(gt=0)
    wheel_radius: float = Field(gt=0)
    wheel_width: float = Field(gt=0)
    wheel_mass: float = Field(gt=0)
    wheelbase: float = Field(gt=0)
    track: float = Field(gt=0)
    wheel_z: float
    top_plate_z: float
    mount_x: float
    max_speed: float = Field(gt=0)
    max_yaw_rate: float = Field(gt=0)
    max_accel: float = Field(gt=0)
    max_yaw_accel: float = Field(gt=0)
    wheel_odometry_slip: float = Field(ge=0)


class D435iSpec(_Spec):
    """The Intel RealSense D435i: colour stream (depth aligned to it) and the stereo depth noise model."""
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    depth_fx: float = Field(gt=0)
    baseline: float = Field(gt=0)
    depth_min: float = Field(ge=0)
    depth_max: float = Field(gt=0)
    subpixel: float = Field(ge=0)
    read_noise: float = Field(ge=0)
    rate: float = Field(gt=0)


class Velodyne32Spec(_Spec):
    """The 32-beam Velodyne (HDL-32E pattern): elevations (deg), azimuth steps per sweep, range model."""
    vertical_deg: list[float] = Field(min_length=1)
    azimuth_steps: int = Field(gt=0)
    rate: float = Field(gt=0)
    range_min: float = Field(ge=0)
    range_max: float = Field(gt=0)
    range_noise: float = Field(ge=0)


class GyroSpec(_Spec):
    """The IMU's yaw-rate gyro (the BMI055's figures)."""
    noise_density_deg_s_rthz: float = Field(ge=0)
    zero_rate_offset_deg_s: float = Field(ge=0)
    bias_walk_deg_s_rts: float = Field(ge=0)
    calibration_s: float = Field(gt=0)


class HardwareSpec(_Spec):
    jackal: JackalSpec
    d435i: D435iSpec
    velodyne: Velodyne32Spec
    gyro: GyroSpec


class HardwareError(ValueError):
    """``hardware.toml`` is unreadable or a figure is missing, unknown or of the wrong type."""


def load_hardware(path: str | os.PathLike = HARDWARE_TOML) -> HardwareSpec:
    """The typed spec from a hardware TOML file; ``HardwareError`` names the file, section and field."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise HardwareError(f"{path}: expected a readable hardware TOML file: {exc}") from None
    try:
        return HardwareSpec.model_validate(data)
    except ValidationError as exc:
        e = exc.errors()[0]
        where = ".".join(str(x) for x in e["loc"])
        raise HardwareError(f"{path}: [{where}]: {e['msg']}") from None


@functools.lru_cache(maxsize=1)
def hardware_spec() -> HardwareSpec:
    """The bundled hardware (``sim/data/hardware.toml``), read once."""
    return load_hardware()
