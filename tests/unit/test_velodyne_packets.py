"""VLP-32C data packets (``stack.velodyne``): the layout, the decoding's geometry and times, the
checks on foreign bytes, and packing a sweep back on its packets bit for bit."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from stack.velodyne import (BLOCKS, LASERS, PACKET_BYTES, VLP32C, PacketError, VelodynePackets, build_packets,
                            decode_sweep, encode_like, parse_packets)


def _one_return(block=3, laser=5, azimuth=9000, count=1250, refl=77, packets=2, stamp_ns=5_000_000_000):
    az = np.tile(np.arange(BLOCKS) * 20, (packets, 1)) + np.arange(packets)[:, None] * 240
    az[1 % packets, block] = azimuth
    counts = np.zeros((packets, BLOCKS, LASERS), dtype=np.int64)
    reflectivity = np.zeros_like(counts)
    counts[1 % packets, block, laser] = count
    reflectivity[1 % packets, block, laser] = refl
    stamps = stamp_ns + np.arange(packets, dtype=np.int64) * 663_552
    return build_packets(az, counts, reflectivity, stamps), stamp_ns


def test_the_packet_layout_is_the_sensors():
    pk, _ = _one_return()
    assert pk.data.shape == (2, PACKET_BYTES) and pk.data.dtype == np.uint8
    blocks = pk.data[:, :1200].reshape(2, BLOCKS, 100)
    assert np.all(blocks[..., 0] == 0xFF) and np.all(blocks[..., 1] == 0xEE)
    assert tuple(pk.data[1, 100 * 3 + 2: 100 * 3 + 4]) == (9000 & 0xFF, 9000 >> 8)  # little endian
    first = 100 * 3 + 4 + 3 * 5
    assert tuple(pk.data[1, first: first + 3]) == (1250 & 0xFF, 1250 >> 8, 77)
    assert np.all(pk.data[:, 1204] == 0x37) and np.all(pk.data[:, 1205] == 0x28)
    az, counts, refl = parse_packets(pk.data)
    assert az[1, 3] == 9000 and counts[1, 3, 5] == 1250 and refl[1, 3, 5] == 77 and counts.sum() == 1250


def test_one_return_decodes_to_its_point_time_and_ring():
    pk, stamp_ns = _one_return(block=3, laser=5, azimuth=9000, count=1250)
    scan = decode_sweep(pk, stamp_ns)
    assert scan.points.shape == (1, 3) and scan.points.dtype == np.float32
    r = 1250 * 0.004  # 5 m
    heading = np.radians(90.0 + VLP32C.azimuth_offset_deg[5])  # laser 5: elevation 0, offset -1.4 deg
    np.testing.assert_allclose(scan.points[0], [r * np.cos(heading), -r * np.sin(heading), 0.0], atol=1e-6)
    assert scan.points[0, 1] < -4.9  # 90 deg clockwise from the front: the sensor's right (ROS -y)
    # packet 1's stamp, block 3, laser pair 2 (lasers 4 and 5)
    assert scan.times_s[0] == pytest.approx(663_552e-9 + 3 * 55.296e-6 + 2 * 2.304e-6, abs=1e-12)
    assert scan.ring[0] == 20  # elevation 0 deg is the 21st lowest of the VLP-32C's lasers
    assert scan.intensity[0] == 77 and scan.stamp == pytest.approx(5.0)


def test_rings_number_the_lasers_by_elevation():
    ring = VLP32C.ring_of_laser
    assert sorted(ring.tolist()) == list(range(LASERS))
    assert ring[0] == 0 and ring[29] == 31  # -25 deg lowest, +15 deg highest
    el = np.asarray(VLP32C.vertical_deg)
    assert np.all(np.diff(el[VLP32C.laser_of_ring]) > 0)


@pytest.mark.parametrize("change, expected", [
    (lambda d: d[:, :1000], "1206 bytes each"),
    (lambda d: _set(d, 1205, 0x22), "product ID 0x22"),
    (lambda d: _set(d, 1204, 0x39), "return mode 0x39"),
    (lambda d: _set(d, 1, 0x00), "flag FF EE"),
    (lambda d: _set(d, 3, 0xFF), "block azimuth"),
])
def test_bytes_that_are_not_vlp32c_packets_are_refused(change, expected):
    pk, stamp_ns = _one_return()
    with pytest.raises(PacketError, match=expected):
        decode_sweep(VelodynePackets(change(pk.data.copy()), pk.stamps_ns), stamp_ns)


def _set(data, index, value):
    data[:, index] = value
    return data


def _sweep(seed=0, packets=151):
    """A sweep of random returns on a layout like the simulator's (some lasers without a return)."""
    rng = np.random.default_rng(seed)
    A = packets * BLOCKS
    az = ((18000 + np.rint(36000.0 * np.arange(A) / A)) % 36000).astype(np.int64).reshape(packets, BLOCKS)
    counts = rng.integers(100, 20000, (packets, BLOCKS, LASERS)) * (rng.random((packets, BLOCKS, LASERS)) > 0.2)
    refl = rng.integers(0, 256, (packets, BLOCKS, LASERS))
    stamps = 7_000_000_000 + np.rint(np.arange(packets) * 12 * (0.1 / A) * 1e9).astype(np.int64)
    pk = build_packets(az, counts, refl * (counts > 0), stamps)
    return pk, decode_sweep(pk, 7_000_000_000)


def test_a_sweep_packs_back_on_its_packets_bit_for_bit():
    pk, scan = _sweep()
    assert len(scan.points) > 40_000  # of 57,984 returns
    out = encode_like(pk, scan)
    assert np.array_equal(out.data, pk.data) and np.array_equal(out.stamps_ns, pk.stamps_ns)


def test_part_of_a_sweep_packs_on_the_same_blocks():
    pk, scan = _sweep(1)
    keep = np.random.default_rng(2).random(len(scan.points)) > 0.5
    part = replace(scan, points=scan.points[keep], times_s=scan.times_s[keep], ring=scan.ring[keep],
                   intensity=scan.intensity[keep])
    back = decode_sweep(encode_like(pk, part), 7_000_000_000)
    assert np.array_equal(back.points, part.points) and np.array_equal(back.times_s, part.times_s)


@pytest.mark.parametrize("spoil", [
    lambda s: replace(s, points=s.points * np.float32(1.0001)),  # ranges off the 4 mm steps
    lambda s: replace(s, intensity=s.intensity + np.float32(0.5)),  # not a byte
    lambda s: replace(s, ring=None),
])
def test_points_that_are_not_the_sensors_returns_are_refused(spoil):
    pk, scan = _sweep(3, packets=20)
    with pytest.raises(PacketError):
        encode_like(pk, spoil(scan))


def test_the_simulated_velodyne_publishes_packets_that_decode_to_its_sweep():
    from sim.episode import Episode
    from stack.messages import LidarScan

    sweeps = {}
    for packets in (False, True):
        with Episode(None, duration=0.5, camera=False, lidar_packets=packets) as ep:
            sweeps[packets] = [m for m in ep.frames() if isinstance(m, LidarScan)]
    a, b = sweeps[False][-1], sweeps[True][-1]
    assert b.packets is not None and b.packets.data.shape == (151, PACKET_BYTES) and a.packets is None
    assert abs(len(a.points) - len(b.points)) < 0.01 * len(a.points)  # the same room, seen the same way
    assert b.stamp == pytest.approx(a.stamp, abs=1e-9) and b.times_s.max() < 0.1
    ranges = np.linalg.norm(b.points.astype(np.float64), axis=1)
    steps = ranges / 0.004
    assert np.abs(steps - np.rint(steps)).max() < 1e-3  # every range on the sensor's 4 mm steps
    again = decode_sweep(encode_like(b.packets, b), int(round(b.stamp * 1e9)))
    assert np.array_equal(again.points, b.points) and np.array_equal(again.times_s, b.times_s)


def _packet_bag(path, sweeps):
    """A bag of VelodyneScan messages only, each sweep (packets, stamp_ns) as given."""
    from testbed.bags import BagWriter
    from testbed.bags import topics as T
    from testbed.bags.convert import VELODYNE_SCAN, velodyne_scan

    with BagWriter(path) as w:
        for pk, stamp_ns in sweeps:
            w.write_message(T.LIDAR_PACKETS, VELODYNE_SCAN, stamp_ns * 1e-9,
                            velodyne_scan(w.dialect, stamp_ns, "velodyne", pk.data, pk.stamps_ns))
    return path


@pytest.mark.parametrize("name", ["b.bag", "b"])
def test_a_bag_of_packets_reads_back_as_its_sweeps_and_skips_a_bad_one(tmp_path, name):
    from testbed.bags import BagReader

    sweeps = []
    for k in range(12):
        pk, _ = _sweep(k, packets=10)
        stamp_ns = 1_000_000_000 + k * 100_000_000
        pk = VelodynePackets(pk.data, pk.stamps_ns - 7_000_000_000 + stamp_ns)
        if k == 5:  # an HDL-32E's packet among the VLP-32C's
            pk.data[3, 1205] = 0x21
        sweeps.append((pk, stamp_ns))
    bag = _packet_bag(tmp_path / name, sweeps)
    with BagReader(bag, require_camera=False, T_base_lidar=np.eye(4)) as r:
        scans = list(r.scans())
        bad = r.bad_message_summary()
    assert len(scans) == 11
    assert list(bad.values())[0]["count"] == 1 and "product ID 0x21" in list(bad.values())[0]["reason"]
    for scan, (pk, stamp_ns) in zip(scans, [s for k, s in enumerate(sweeps) if k != 5]):
        want = decode_sweep(pk, stamp_ns)
        assert scan.stamp == want.stamp and np.array_equal(scan.points, want.points)
        assert np.array_equal(scan.times_s, want.times_s) and np.array_equal(scan.ring, want.ring)


def test_replay_of_a_bag_of_foreign_packets_stops_with_one_line(tmp_path, capsys):
    from testbed.cli import main

    sweeps = []
    for k in range(3):
        pk, _ = _sweep(k, packets=4)
        pk.data[:, 1204] = 0x39  # dual return
        sweeps.append((pk, 1_000_000_000 + k * 100_000_000))
    bag = _packet_bag(tmp_path / "dual", sweeps)
    assert main(["replay", str(bag), "--out", str(tmp_path / "out"), "--odometry-only",
                 "--T-base-lidar", "0,0,0,0,0,0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "return mode 0x39" in err[0] and "Traceback" not in err[0]
