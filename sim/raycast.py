"""An analytic LiDAR ray caster for a world of boxes (``BoxRayCaster``).

PyBullet's ``rayTestBatch`` costs ~110-150 ms per full 32 x 1808 sweep on these machines, more than
the sweep itself lasts. The static world is made of boxes (``sim.world.Box``), so rays are cast here
against those boxes exactly (slab test), each box tested only against the azimuth columns and the rings it
can reach. The caster holds the same boxes PyBullet holds; ``tests/unit/test_sim_lidar.py`` checks both agree.

Motion skew: each azimuth column fires at its own time within the sweep, from the sensor pose at that
time; the points are reported in the sensor frame at their firing time, as a real spinning LiDAR does.
The sensor (its beam pattern) is ``sim.lidar``.
"""
from __future__ import annotations

import numpy as np


_TWO_PI = 2 * np.pi


def _slices(mask: np.ndarray) -> list[slice]:
    """Slices covering the True entries of a 1-D mask: one bounding slice, or two when it wraps around."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    n = mask.size
    if idx.size == n:
        return [slice(0, n)]
    if mask[0] and mask[-1]:  # wraps: cover [0, first gap) and (last gap, n)
        gaps = np.flatnonzero(~mask)
        return [slice(0, int(gaps[0])), slice(int(gaps[-1]) + 1, n)]
    return [slice(int(idx[0]), int(idx[-1]) + 1)]


class BoxRayCaster:
    """Exact ray casting against oriented boxes (slab test), culled per box by azimuth and elevation.

    Most boxes of a scene stand upright (one axis along world z: walls, furniture, standing objects);
    for those the z slab is shared by all boxes (one reciprocal of the rays' z components per cast) and
    only the two horizontal slabs are box specific. Other boxes take the general three-slab test.
    """

    def __init__(self, boxes):
        self.boxes = list(boxes)
        if not self.boxes:
            raise ValueError("BoxRayCaster needs at least one box")
        self.R = np.stack([np.asarray(b.T_world_box, dtype=float)[:3, :3] for b in self.boxes])
        self.c = np.stack([np.asarray(b.T_world_box, dtype=float)[:3, 3] for b in self.boxes])
        self.half = np.stack([np.asarray(b.half, dtype=float) for b in self.boxes])
        self.refl = np.array([b.reflectivity for b in self.boxes])
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        self.corners = np.einsum("bij,bkj->bki", self.R, signs[None] * self.half[:, None, :]) + self.c[:, None, :]
        self.aabb_lo = self.corners.min(axis=1)
        self.aabb_hi = self.corners.max(axis=1)
        # upright boxes: (horizontal axis u, its half extent, the other horizontal half extent)
        self.upright = np.zeros(len(self.boxes), dtype=bool)
        self.u = np.zeros((len(self.boxes), 2))
        self.hu = np.zeros(len(self.boxes))
        self.hv = np.zeros(len(self.boxes))
        for b, R in enumerate(self.R):
            k = int(np.argmax(np.abs(R[2])))
            if abs(R[2, k]) > 1 - 1e-9:
                i, j = [a for a in range(3) if a != k]
                self.upright[b] = True
                self.u[b] = R[:2, i] / np.linalg.norm(R[:2, i])
                self.hu[b], self.hv[b] = self.half[b, i], self.half[b, j]

    def cast(self, origins: np.ndarray, dirs: np.ndarray, azimuth_world: np.ndarray | None = None,
             max_range: float = 200.0):
        """Ranges (A, R) (inf: no hit) and the index of the box hit (-1: none), for rays origins + t * dirs.

        ``dirs`` is (A, R, 3): A azimuth columns of R rays each (unit vectors: the range is t). ``origins``
        is (A, 3) (one origin per column) or broadcastable to ``dirs``. When ``azimuth_world`` (A,) gives
        each column's heading, boxes are tested only against the columns they can cover.
        """
        dirs = np.asarray(dirs, dtype=float)
        A, Rr, _ = dirs.shape
        o = np.asarray(origins, dtype=float)
        if o.shape == (A, 3):
            o = o[:, None, :]
        else:
            o = np.broadcast_to(o, dirs.shape)
            if o.strides[1] == 0 or np.array_equal(o, np.broadcast_to(o[:, :1], o.shape)):
                o = o[:, :1]
        ox, oy, oz = (np.ascontiguousarray(o[..., k]) for k in range(3))
        dx, dy, dz = (np.ascontiguousarray(dirs[..., k]) for k in range(3))
        return self.cast_components(ox, oy, oz, dx, dy, dz, azimuth_world, max_range)

    def cast_components(self, ox, oy, oz, dx, dy, dz, azimuth_world=None, max_range: float = 200.0,
                        azimuth_spread: float = 0.0):
        """``cast`` on split components: origins (A, 1) or (A, R) each, directions (A, R) each.
        ``azimuth_spread`` (rad): how far any ray of a column may head from ``azimuth_world`` besides
        the sensor's tilt (a sensor whose lasers have azimuth offsets)."""
        A, Rr = dx.shape
        best = np.full((A, Rr), np.inf)
        hit = np.full((A, Rr), -1, dtype=np.int32)
        per_ray = ox.shape[1] > 1
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_dz = 1.0 / dz
            cols = self._column_slices(ox, oy, dx, dy, dz, azimuth_world, azimuth_spread)
            rings = self._ring_slices(ox, oy, oz, dx, dy, dz)
            for b in range(len(self.boxes)):
                rs = rings[b]
                if rs is None:
                    continue
                for cs in cols[b]:
                    oxs, oys, ozs = ((v[cs, rs] if per_ray else v[cs]) for v in (ox, oy, oz))
                    dxs, dys, dzs = dx[cs, rs], dy[cs, rs], dz[cs, rs]
                    if self.upright[b]:
                        tn, tf = self._upright_slabs(b, oxs, oys, ozs, dxs, dys, inv_dz[cs, rs])
                    else:
                        tn, tf = self._general_slabs(b, oxs, oys, ozs, dxs, dys, dzs)
                    cur = best[cs, rs]
                    better = (tn <= tf) & (tn > 1e-6) & (tn < cur)
                    np.copyto(cur, tn, where=better)
                    np.copyto(hit[cs, rs], np.int32(b), where=better)
        best[best > max_range] = np.inf
        hit[~np.isfinite(best)] = -1
        return best, hit

    # --- slab tests --------------------------------------------------------------------------------
    def _upright_slabs(self, b, ox, oy, oz, dx, dy, inv_dz):
        ux, uy = self.u[b]
        rx, ry = ox - self.c[b, 0], oy - self.c[b, 1]
        tn, tf = _slab(rx * ux + ry * uy, dx * ux + dy * uy, self.hu[b])
        n2, f2 = _slab(ry * ux - rx * uy, dy * ux - dx * uy, self.hv[b])
        np.maximum(tn, n2, out=tn)
        np.minimum(tf, f2, out=tf)
        ta = (self.aabb_lo[b, 2] - oz) * inv_dz
        tb = (self.aabb_hi[b, 2] - oz) * inv_dz
        np.maximum(tn, np.minimum(ta, tb), out=tn)
        np.minimum(tf, np.maximum(ta, tb), out=tf)
        return tn, tf

    def _general_slabs(self, b, ox, oy, oz, dx, dy, dz):
        R, c = self.R[b], self.c[b]
        tn = tf = None
        for k in range(3):
            ol = (ox - c[0]) * R[0, k] + (oy - c[1]) * R[1, k] + (oz - c[2]) * R[2, k]
            dl = dx * R[0, k] + dy * R[1, k] + dz * R[2, k]
            n, f = _slab(ol, dl, self.half[b, k])
            if tn is None:
                tn, tf = n, f
            else:
                np.maximum(tn, n, out=tn)
                np.minimum(tf, f, out=tf)
        return tn, tf

    # --- culling -----------------------------------------------------------------------------------
    def _column_slices(self, ox, oy, dx, dy, dz, azimuth_world, azimuth_spread: float = 0.0) -> list[list[slice]]:
        """Per box, the column slices whose rays can reach it (all columns without ``azimuth_world``)."""
        A = dx.shape[0]
        B = len(self.boxes)
        if azimuth_world is None or A < 2:
            return [[slice(0, A)]] * B
        az = np.asarray(azimuth_world, dtype=float)
        om = np.array([ox.mean(), oy.mean()])
        spread = max(float(np.ptp(ox)), float(np.ptp(oy)))
        # how far the rays' own azimuths stray from the column heading (a tilted sensor): the extreme rings
        mean_z = dz.mean(axis=0)
        stray = 0.0
        for r in {int(np.argmin(mean_z)), int(np.argmax(mean_z))}:
            d = (np.arctan2(dy[:, r], dx[:, r]) - az + np.pi) % _TWO_PI - np.pi
            stray = max(stray, float(np.abs(d).max()))
        stray += float(azimuth_spread)  # the lasers' own offsets on top of the tilt (over-estimated: safe)
        rel = self.corners[:, :, :2] - om
        ang = np.arctan2(rel[..., 1], rel[..., 0])
        cen = 0.5 * (self.aabb_lo[:, :2] + self.aabb_hi[:, :2]) - om
        mid = np.arctan2(cen[:, 1], cen[:, 0])
        d = (ang - mid[:, None] + np.pi) % _TWO_PI - np.pi
        half_xy = 0.5 * (self.aabb_hi[:, :2] - self.aabb_lo[:, :2])
        inside = np.all(np.abs(cen) < half_xy + spread + 0.05, axis=1)
        wide = np.ptp(d, axis=1) > 0.95 * np.pi
        dist = np.linalg.norm(cen, axis=1)
        margin = 0.02 + stray + np.arctan2(spread + 0.02, np.maximum(dist - np.linalg.norm(half_xy, axis=1), 0.05))
        lo = mid + d.min(axis=1) - margin
        width = d.max(axis=1) - d.min(axis=1) + 2 * margin
        mask = (az[None, :] - lo[:, None]) % _TWO_PI <= width[:, None]
        mask[inside | wide] = True
        return [_slices(m) for m in mask]

    def _ring_slices(self, ox, oy, oz, dx, dy, dz) -> list[slice | None]:
        """Per box, the ring slice whose elevations can reach it (None: no ring can)."""
        sin_el = dz / np.sqrt(dx * dx + dy * dy + dz * dz)
        s_lo, s_hi = sin_el.min(axis=0), sin_el.max(axis=0)  # (R,) over the columns
        om = np.array([ox.mean(), oy.mean()])
        spread = max(float(np.ptp(ox)), float(np.ptp(oy)))
        cen = 0.5 * (self.aabb_lo[:, :2] + self.aabb_hi[:, :2])
        half_xy = 0.5 * (self.aabb_hi[:, :2] - self.aabb_lo[:, :2])
        r_min = np.maximum(np.linalg.norm(np.maximum(np.abs(om - cen) - half_xy, 0.0), axis=1) - spread, 0.0)
        r_max = np.linalg.norm(om - cen, axis=1) + np.linalg.norm(half_xy, axis=1) + spread
        zt = self.aabb_hi[:, 2] - float(oz.min())  # highest point over the lowest origin
        zb = self.aabb_lo[:, 2] - float(oz.max())
        r_t = np.where(zt >= 0, r_min, r_max)
        r_b = np.where(zb <= 0, r_min, r_max)
        box_hi = zt / np.maximum(np.hypot(zt, r_t), 1e-12)
        box_lo = zb / np.maximum(np.hypot(zb, r_b), 1e-12)
        ok = (s_hi[None, :] >= box_lo[:, None] - 1e-9) & (s_lo[None, :] <= box_hi[:, None] + 1e-9)  # (B, R)
        out = []
        for m in ok:
            idx = np.flatnonzero(m)
            out.append(slice(int(idx[0]), int(idx[-1]) + 1) if idx.size else None)
        return out


def _slab(o, d, h):
    """Entry and exit parameters of rays o + t d through the slab |x| <= h (inf/-inf when parallel)."""
    inv = 1.0 / d
    ta = (-h - o) * inv
    tb = (h - o) * inv
    return np.minimum(ta, tb), np.maximum(ta, tb)
