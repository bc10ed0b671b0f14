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


@dataclass
class PacketLayout:
    """How a sweep of ``BeamPattern`` fills VLP-32C data packets (``stack.velodyne``): column k is
    block k % 12 of packet k // 12, at azimuth 180 deg + 360 deg * k / A in the sensor's 0.01 deg
    (clockwise from the front, the Velodyne's own convention, so column 0 points behind the sensor as
    in ``BeamPattern.azimuths``); the last packet's unused blocks repeat the last azimuth with no
    returns. Packet p is stamped 12 p A-th parts of the period after the sweep's stamp (to the ns)."""

    beams: BeamPattern

    def __post_init__(self):
        from stack.velodyne import BLOCKS, VLP32C

        self.model = VLP32C
        if sorted(self.model.vertical_deg) != sorted(float(v) for v in self.beams.vertical_deg):
            raise ValueError("the Velodyne's elevations in hardware.toml are not the VLP-32C's: packets need them")
        A = self.beams.azimuth_steps
        self.columns = A
        self.packets = -(-A // BLOCKS)
        k = np.minimum(np.arange(self.packets * BLOCKS), A - 1)
        self.azimuth_centideg = ((18000 + np.rint(36000.0 * k / A).astype(np.int64)) % 36000).reshape(-1, BLOCKS)
        self.offsets_ns = np.rint(np.arange(self.packets) * BLOCKS * (self.beams.period / A) * 1e9).astype(np.int64)

    def directions(self) -> np.ndarray:
        """(A, R, 3) unit ray directions in ring order (rings sorted by elevation, as ``BeamPattern``)."""
        d = self.model.directions(self.azimuth_centideg.reshape(-1)[: self.columns])  # (A, 32, 3) laser order
        return d[:, self.model.laser_of_ring]

    def azimuths(self) -> np.ndarray:
        """Column headings (rad, counter-clockwise, sensor frame): the blocks' azimuths."""
        return -np.radians(self.azimuth_centideg.reshape(-1)[: self.columns] / 100.0)

    def column_times(self) -> np.ndarray:
        """Each column's firing time after the sweep's stamp: its block's time as the decoder gives it."""
        from stack.velodyne import BLOCKS

        t = self.offsets_ns[:, None] * 1e-9 + np.arange(BLOCKS) * self.model.firing_period_s
        return t.reshape(-1)[: self.columns]
