"""The 32-beam Velodyne: beam pattern from ``data/hardware.toml`` and an analytic ray caster.

PyBullet's ``rayTestBatch`` costs ~110-150 ms per full 32 x 1808 sweep on these machines, more than
the sweep itself lasts. The static world is made of boxes (``sim.world.Box``), so rays are cast here
against those boxes exactly (slab test), with each box tested only against the azimuth columns it can
cover. The caster holds the same boxes PyBullet holds; ``tests/test_lidar.py`` checks both agree.

Motion skew: each azimuth column fires at its own time within the sweep, from the sensor pose at that
time; the points are reported in the sensor frame at their firing time, as a real spinning LiDAR does.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.camera import hardware


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
        h = hardware()["velodyne"]
        return BeamPattern(np.array(h["vertical_deg"], dtype=float), int(azimuth_steps or h["azimuth_steps"]),
                           float(rate or h["rate"]), h["range_min"], h["range_max"], h["range_noise"])

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


def _az_interval(corners_xy: np.ndarray, origin_xy: np.ndarray):
    """Azimuth interval [lo, hi] (rad, hi - lo < 2 pi) covering a box's corners from origin, or None for all."""
    rel = corners_xy - origin_xy
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    mid = np.arctan2(rel[:, 1].mean(), rel[:, 0].mean())
    d = (ang - mid + np.pi) % (2 * np.pi) - np.pi
    if np.ptp(d) > np.pi * 0.95:
        return None
    return mid + d.min(), mid + d.max()


class BoxRayCaster:
    def __init__(self, boxes):
        self.boxes = list(boxes)
        self.R = np.stack([b.T_world_box[:3, :3] for b in self.boxes])
        self.c = np.stack([b.T_world_box[:3, 3] for b in self.boxes])
        self.half = np.stack([b.half for b in self.boxes])
        self.refl = np.array([b.reflectivity for b in self.boxes])
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        self.corners = np.einsum("bij,bkj->bki", self.R, signs[None] * self.half[:, None, :]) + self.c[:, None, :]

    def cast(self, origins: np.ndarray, dirs: np.ndarray, azimuth_world: np.ndarray | None = None,
             max_range: float = 200.0):
        """Ranges (N,) (inf: no hit) and the index of the box hit, for rays origins + t * dirs.

        ``origins``/``dirs`` are (A, R, 3) arrays of A azimuth columns; when ``azimuth_world`` (A,)
        gives each column's heading, boxes are tested only against the columns they can cover.
        """
        A, Rr, _ = dirs.shape
        best = np.full((A, Rr), np.inf)
        hit = np.full((A, Rr), -1, dtype=np.int32)
        o_mean = origins.reshape(-1, 3).mean(axis=0)
        spread = np.ptp(origins.reshape(-1, 3)[:, :2], axis=0).max() if A > 1 else 0.0
        for b in range(len(self.boxes)):
            cols = slice(None)
            if azimuth_world is not None:
                inside = np.all(np.abs(self.R[b].T @ (o_mean - self.c[b])) < self.half[b] + spread + 0.05)
                iv = None if inside else _az_interval(self.corners[b][:, :2], o_mean[:2])
                if iv is not None:
                    dist = np.linalg.norm(self.c[b][:2] - o_mean[:2])
                    margin = 0.02 + np.arctan2(spread + 0.02, max(dist - np.linalg.norm(self.half[b][:2]), 0.05))
                    lo, hi = iv[0] - margin, iv[1] + margin
                    rel = (azimuth_world - lo) % (2 * np.pi)
                    sel = np.nonzero(rel <= (hi - lo))[0]
                    if sel.size == 0:
                        continue
                    cols = sel
            o = origins[cols] - self.c[b]
            d = dirs[cols]
            ol = o @ self.R[b]
            dl = d @ self.R[b]
            with np.errstate(divide="ignore", invalid="ignore"):
                inv_d = 1.0 / dl
                t1 = (-self.half[b] - ol) * inv_d
                t2 = (self.half[b] - ol) * inv_d
            tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
            ok = (tmax >= tmin) & (tmin > 1e-6)
            tsel = np.where(ok, tmin, np.inf)
            cur = best[cols]
            better = tsel < cur
            if better.any():
                best[cols] = np.where(better, tsel, cur)
                hit[cols] = np.where(better, b, hit[cols])
        best[best > max_range] = np.inf
        return best, hit
