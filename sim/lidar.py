"""The 32-beam Velodyne: its beam pattern from ``data/hardware.toml`` (``BeamPattern``). The rays are
cast by ``sim.raycast.BoxRayCaster`` (importable from here too).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.raycast import BoxRayCaster  # noqa: F401 (re-exported)
from sim.sensors import hardware_spec


@dataclass
class BeamPattern:
    vertical_deg: np.ndarray  # (R,)
    azimuth_steps: int
    rate: float
    range_min: float
    range_max: float
    range_noise: float

    @staticmethod
    def from_hardware(azimuth_steps: int | None = None, rate: float | None = None) -> "BeamPattern":
        h = hardware_spec().velodyne
        return BeamPattern(np.array(h.vertical_deg, dtype=float), int(azimuth_steps or h.azimuth_steps),
                           float(rate or h.rate), h.range_min, h.range_max, h.range_noise)

    @property
    def period(self) -> float:
        return 1.0 / self.rate

    def azimuths(self) -> np.ndarray:
        """Column azimuths (rad, sensor frame): clockwise seen from above, starting behind the sensor."""
        k = np.arange(self.azimuth_steps)
        return np.pi - 2 * np.pi * k / self.azimuth_steps

    def column_times(self) -> np.ndarray:
        return np.arange(self.azimuth_steps) * (self.period / self.azimuth_steps)

    def directions(self) -> np.ndarray:
        """(A, R, 3) unit ray directions in the sensor frame."""
        az = self.azimuths()[:, None]
        el = np.radians(self.vertical_deg)[None, :]
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], axis=-1)
