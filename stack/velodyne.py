"""The Velodyne VLP-32C's data packets (``velodyne_msgs/VelodyneScan``), decoded to a sweep.

What a robot records when it keeps the LiDAR's raw output: per sweep, the UDP payloads of the
sensor, 1206 bytes each: 12 firing blocks (flag ``FF EE``, the block's azimuth in 0.01 deg, then
32 returns of a 16-bit distance in 4 mm steps and an 8-bit calibrated reflectivity, in laser-ID
order), a 4-byte timestamp and two factory bytes (return mode, product ID ``0x28``). A return's
distance 0 means no return.

The decoding follows ``velodyne_pointcloud`` for this model: each laser's elevation and azimuth
offset from the VLP-32C's published table, the block's azimuth plus the laser's offset as the
beam's heading, ROS axes (x forward, y left, z up), no per-laser azimuth interpolation. Each point's
time is its packet's stamp, plus 55.296 us per block and 2.304 us per laser pair (the lasers fire
two at a time). ``ring`` is the laser's rank by elevation (0 = lowest), as velodyne_pointcloud
numbers rings.

The simulator's Velodyne in packet mode publishes exactly these packets and its sweep *is* their
decoding, so a bag of packets replays to the same points, bit for bit, as the live run saw.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .messages import LidarScan

PACKET_BYTES = 1206
BLOCKS = 12
LASERS = 32
BLOCK_BYTES = 100
PRODUCT_VLP32C = 0x28
RETURN_MODES = {0x37: "strongest", 0x38: "last"}  # single-return modes; 0x39 (dual) is not decoded

# The VLP-32C's lasers in ID order (the order of the returns in a block): elevation and azimuth
# offset in degrees (Velodyne's VLP-32C user manual).
VLP32C_VERTICAL_DEG = (-25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843, -7.254, 0.333, -0.333,
                       -6.148, -5.333, 1.333, 0.667, -4.0, -4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333,
                       -2.667, -3.0, 7.0, 4.667, -2.333, -2.0, 15.0, 10.333, -1.333)
VLP32C_AZIMUTH_OFFSET_DEG = (1.4, -4.2, 1.4, -1.4, 1.4, -1.4, 4.2, -1.4, 1.4, -4.2, 1.4, -1.4, 4.2, -1.4, 4.2,
                             -1.4, 1.4, -4.2, 1.4, -4.2, 4.2, -1.4, 1.4, -1.4, 1.4, -1.4, 1.4, -4.2, 4.2, -1.4,
                             1.4, -1.4)


class PacketError(ValueError):
    """Bytes that are not a VLP-32C's single-return data packets; the message says what was expected."""


@dataclass(frozen=True)
class Vlp32c:
    """The sensor model the packets are decoded with (the published VLP-32C figures by default)."""

    vertical_deg: tuple[float, ...] = VLP32C_VERTICAL_DEG
    azimuth_offset_deg: tuple[float, ...] = VLP32C_AZIMUTH_OFFSET_DEG
    distance_resolution: float = 0.004  # m per count
    firing_period_s: float = 55.296e-6  # one block: all 32 lasers fired and recharged
    pair_period_s: float = 2.304e-6  # lasers fire two at a time, a pair every 2.304 us

    @property
    def ring_of_laser(self) -> np.ndarray:
        """(32,) ring (rank by elevation, 0 = lowest) of each laser ID."""
        order = np.argsort(np.asarray(self.vertical_deg), kind="stable")
        ring = np.empty(LASERS, dtype=np.uint16)
        ring[order] = np.arange(LASERS, dtype=np.uint16)
        return ring

    @property
    def laser_of_ring(self) -> np.ndarray:
        """(32,) laser ID of each ring."""
        return np.argsort(np.asarray(self.vertical_deg), kind="stable")

    def laser_times(self) -> np.ndarray:
        """(32,) firing time of each laser after its block's start, s."""
        return (np.arange(LASERS) // 2) * self.pair_period_s

    def directions(self, azimuth_centideg: np.ndarray) -> np.ndarray:
        """(..., 32, 3) unit beam directions (ROS axes, laser-ID order) of blocks at these azimuths."""
        az = np.asarray(azimuth_centideg, dtype=np.float64)[..., None] / 100.0
        heading = np.radians(az + np.asarray(self.azimuth_offset_deg))
        el = np.radians(np.asarray(self.vertical_deg))
        c = np.cos(el)
        return np.stack([c * np.cos(heading), -c * np.sin(heading), np.broadcast_to(np.sin(el), heading.shape)],
                        axis=-1)

    def max_azimuth_offset_rad(self) -> float:
        return float(np.radians(np.max(np.abs(self.azimuth_offset_deg))))


VLP32C = Vlp32c()


@dataclass
class VelodynePackets:
    """One sweep's packets: ``data`` (P, 1206) uint8, ``stamps_ns`` (P,) int64 (each packet's stamp)."""

    data: np.ndarray
    stamps_ns: np.ndarray


def build_packets(azimuth_centideg: np.ndarray, counts: np.ndarray, reflectivity: np.ndarray,
                  stamps_ns: np.ndarray, return_mode: int = 0x37) -> VelodynePackets:
    """Packets from per-block arrays: ``azimuth_centideg`` (P, 12), ``counts`` (P, 12, 32) distance
    counts in laser-ID order (0: no return), ``reflectivity`` (P, 12, 32) 0-255, ``stamps_ns`` (P,)."""
    az = np.asarray(azimuth_centideg)
    P = az.shape[0]
    if az.shape != (P, BLOCKS) or np.asarray(counts).shape != (P, BLOCKS, LASERS):
        raise PacketError(f"blocks of shape {az.shape} and returns of {np.asarray(counts).shape}: expected "
                          f"(P, {BLOCKS}) and (P, {BLOCKS}, {LASERS})")
    blocks = np.zeros((P, BLOCKS, BLOCK_BYTES), dtype=np.uint8)
    blocks[..., 0], blocks[..., 1] = 0xFF, 0xEE
    blocks[..., 2:4] = az.astype("<u2")[..., None].view(np.uint8)
    ret = blocks[..., 4:].reshape(P, BLOCKS, LASERS, 3)
    ret[..., 0:2] = np.asarray(counts).astype("<u2")[..., None].view(np.uint8)
    ret[..., 2] = reflectivity
    data = np.zeros((P, PACKET_BYTES), dtype=np.uint8)
    data[:, :BLOCKS * BLOCK_BYTES] = blocks.reshape(P, -1)
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    us_past_hour = (stamps // 1000) % 3_600_000_000
    data[:, 1200:1204] = us_past_hour.astype("<u4")[:, None].view(np.uint8)
    data[:, 1204], data[:, 1205] = return_mode, PRODUCT_VLP32C
    return VelodynePackets(data, stamps)


def parse_packets(data: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(azimuth_centideg (P, 12), counts (P, 12, 32), reflectivity (P, 12, 32)) of VLP-32C packets;
    ``PacketError`` for anything else."""
    data = np.asarray(data, dtype=np.uint8)
    if data.ndim != 2 or data.shape[1] != PACKET_BYTES:
        raise PacketError(f"packets of shape {data.shape}: expected {PACKET_BYTES} bytes each")
    P = data.shape[0]
    if P == 0:
        return np.zeros((0, BLOCKS), np.uint16), np.zeros((0, BLOCKS, LASERS), np.uint16), \
            np.zeros((0, BLOCKS, LASERS), np.uint8)
    product, mode = data[:, 1205], data[:, 1204]
    if np.any(product != PRODUCT_VLP32C):
        bad = int(product[product != PRODUCT_VLP32C][0])
        raise PacketError(f"product ID 0x{bad:02x}: expected a VLP-32C's packets (0x{PRODUCT_VLP32C:02x})")
    if not np.all(np.isin(mode, list(RETURN_MODES))):
        bad = int(mode[~np.isin(mode, list(RETURN_MODES))][0])
        raise PacketError(f"return mode 0x{bad:02x}: expected a single-return mode (0x37 strongest, 0x38 last)")
    blocks = data[:, :BLOCKS * BLOCK_BYTES].reshape(P, BLOCKS, BLOCK_BYTES)
    if np.any(blocks[..., 0] != 0xFF) or np.any(blocks[..., 1] != 0xEE):
        raise PacketError("a block without the upper-bank flag FF EE: expected 12 blocks of one VLP-32C each")
    az = np.ascontiguousarray(blocks[..., 2:4]).view("<u2")[..., 0].astype(np.uint16)
    if np.any(az >= 36000):
        raise PacketError(f"block azimuth {int(az.max())}: expected 0-35999 (0.01 deg)")
    ret = blocks[..., 4:].reshape(P, BLOCKS, LASERS, 3)
    counts = np.ascontiguousarray(ret[..., 0:2]).view("<u2")[..., 0].astype(np.uint16)
    return az, counts, ret[..., 2].copy()


_DIRECTIONS: dict = {}  # (model, the blocks' azimuths) -> directions: a sensor at a steady speed repeats them


def _directions(model: Vlp32c, az: np.ndarray) -> np.ndarray:
    key = (model, az.shape, az.tobytes())
    d = _DIRECTIONS.get(key)
    if d is None:
        d = model.directions(az)
        d.setflags(write=False)
        if len(_DIRECTIONS) >= 8:
            _DIRECTIONS.pop(next(iter(_DIRECTIONS)))
        _DIRECTIONS[key] = d
    return d


def decode_sweep(packets: VelodynePackets, stamp_ns: int, model: Vlp32c = VLP32C,
                 frame_id: str = "velodyne") -> LidarScan:
    """The sweep of these packets, stamped ``stamp_ns``: points (float32, ROS axes) in packet, block
    and laser-ID order, per-point times after the stamp, rings, reflectivity as intensity."""
    az, counts, refl = parse_packets(packets.data)
    return decode_blocks(az, counts, refl, packets.stamps_ns, stamp_ns, model, frame_id)


def decode_blocks(az: np.ndarray, counts: np.ndarray, refl: np.ndarray, stamps_ns: np.ndarray, stamp_ns: int,
                  model: Vlp32c = VLP32C, frame_id: str = "velodyne") -> LidarScan:
    """``decode_sweep`` of packets already parsed (``parse_packets``'s arrays and the packet stamps)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if stamps.shape != (az.shape[0],):
        raise PacketError(f"{stamps.shape} packet stamps for {az.shape[0]} packets: expected one each")
    idx = np.flatnonzero(np.asarray(counts).reshape(-1))  # returns, in packet, block, laser order
    block, laser = idx // LASERS, idx % LASERS
    r = np.asarray(counts).reshape(-1)[idx].astype(np.float64) * model.distance_resolution
    dirs = _directions(model, az).reshape(-1, 3)[idx]  # (N, 3)
    points = (dirs * r[:, None]).astype(np.float32)
    block_t = ((stamps - int(stamp_ns)) * 1e-9)[:, None] + np.arange(BLOCKS) * model.firing_period_s  # (P, 12)
    times = block_t.reshape(-1)[block] + model.laser_times()[laser]
    ring = model.ring_of_laser[laser]
    intensity = np.asarray(refl).reshape(-1)[idx].astype(np.float32)
    return LidarScan(float(int(stamp_ns) * 1e-9), points, times, ring.astype(np.uint16), intensity, frame_id)


def encode_like(template: VelodynePackets, scan: LidarScan, model: Vlp32c = VLP32C) -> VelodynePackets:
    """The packets of ``scan`` on the block layout of ``template`` (the sweep the sensor published;
    ``scan`` may hold fewer of its points, e.g. a partial sweep), checked: decoding them gives
    ``scan`` back bit for bit, else ``PacketError`` (points that are not the sensor's returns)."""
    az_t, _, _ = parse_packets(template.data)
    P = az_t.shape[0]
    pts = np.asarray(scan.points, dtype=np.float32)
    n = len(pts)
    if scan.ring is None or scan.intensity is None or len(scan.ring) != n or len(scan.intensity) != n:
        raise PacketError("a scan without per-point ring and intensity: expected the returns of a VLP-32C")
    laser = model.laser_of_ring[np.asarray(scan.ring, dtype=np.int64) % LASERS]
    p64 = pts.astype(np.float64)
    heading = np.degrees(np.arctan2(-p64[:, 1], p64[:, 0]))
    az = np.rint((heading - np.asarray(model.azimuth_offset_deg)[laser]) * 100.0).astype(np.int64) % 36000
    first = np.full(36000, -1, dtype=np.int64)  # azimuth -> its first block (padding repeats the last one)
    flat = az_t.reshape(-1).astype(np.int64)
    first[flat[::-1]] = np.arange(flat.size)[::-1]
    block = first[az]
    counts = np.zeros((P * BLOCKS, LASERS), dtype=np.int64)
    refl = np.zeros((P * BLOCKS, LASERS), dtype=np.int64)
    if n:
        if np.any(block < 0):
            raise PacketError(f"{int((block < 0).sum())} points at azimuths no block of the sweep fired at")
        counts[block, laser] = np.rint(np.linalg.norm(p64, axis=1) / model.distance_resolution)
        refl[block, laser] = np.rint(scan.intensity)
    if counts.max(initial=0) > 0xFFFF or refl.min(initial=0) < 0 or refl.max(initial=0) > 0xFF:
        raise PacketError("a return beyond the packet's 16-bit distance or 8-bit reflectivity")
    mode = int(np.asarray(template.data)[0, 1204]) if P else 0x37
    out = build_packets(az_t, counts.reshape(P, BLOCKS, LASERS), refl.reshape(P, BLOCKS, LASERS),
                        template.stamps_ns, mode)
    back = decode_sweep(out, int(round(scan.stamp * 1e9)), model, scan.frame_id)
    same = (len(back.points) == n and np.array_equal(back.points, pts) and np.array_equal(back.ring, scan.ring)
            and np.array_equal(back.intensity, np.asarray(scan.intensity, dtype=np.float32))
            and np.array_equal(back.times_s, np.asarray(scan.times_s)))
    if not same:
        raise PacketError("the scan's points are not the returns of these packets (quantised ranges, block "
                          "azimuths, laser order): expected a sweep from a sensor that publishes VLP-32C packets")
    return out
