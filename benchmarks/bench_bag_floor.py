"""How small a lossless bag of an episode can be: the sensor noise's entropy, topic by topic.

A lossless bag must keep every bit of what the drivers published, and the simulated sensors publish
their signal plus random noise. The signal is a function of the world and the robot's path, but the
noise is random: no lossless codec can store it in fewer bits than its entropy. This benchmark runs
the default episode without noise (the signals), then computes, for every message, the entropy of
the noise that the sensor models (``sim.camera``, ``sim.lidar``, figures of ``sim/data/hardware.toml``)
would add to that signal:

- colour (``rgb8``): per pixel and channel, the exact entropy of the noisy value given the signal,
  from the model's own noise table (read noise and shot noise, 12-bit quantiles);
- depth (``16UC1``, millimetres): per valid pixel, the entropy of the rounded Gaussian depth noise
  (sigma_z = z^2 * subpixel / (fx * baseline)), plus the random dropouts' binary entropy per pixel;
- LiDAR (``PointCloud2``, float32 x, y, z): per return, the entropy of the Gaussian range noise at
  the resolution of float32 at that point's largest coordinate; ring, time and intensity carry
  no noise. With ``--lidar packets`` (the VLP-32C's data packets, ``stack.velodyne``): per return,
  the entropy of the range noise rounded to the sensor's 4 mm steps.

Printed beside each floor: the bytes per message our recorder writes for that topic (PNG colour,
compressedDepth PNG, PointCloud2; before the MCAP chunks' zstd), measured on a bag of the same
episode, and both scaled to a 60 s bag.

    python benchmarks/bench_bag_floor.py [--duration 10] [--seed 0] [--lidar points|packets]
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def colour_bits_table(read_noise: float) -> np.ndarray:
    """(256,) bits of the noisy colour value given each signal value, exact, from the sensor model's table."""
    from sim.camera import _COLOR_NOISE_BITS, _color_noise_table

    n = 1 << _COLOR_NOISE_BITS
    table = _color_noise_table(float(read_noise)).reshape(256, n)
    bits = np.zeros(256)
    for v in range(256):
        p = np.bincount(table[v], minlength=256) / n
        p = p[p > 0]
        bits[v] = float(-(p * np.log2(p)).sum())
    return bits


def rounded_gaussian_bits(sigma: np.ndarray) -> np.ndarray:
    """Entropy (bits) of round(N(0, sigma)) for each sigma (in units of the rounding step)."""
    from scipy.stats import norm

    s = np.asarray(sigma, dtype=float)
    grid = np.linspace(-3, 1.5, 400)  # log10 sigma
    k = np.arange(-2000, 2001)
    h = []
    for lg in grid:
        sg = 10.0 ** lg
        p = norm.cdf((k + 0.5) / sg) - norm.cdf((k - 0.5) / sg)
        p = p[p > 1e-300]
        h.append(float(-(p * np.log2(p)).sum()))
    h = np.asarray(h)
    big = s > 10.0 ** grid[-1]
    out = np.interp(np.log10(np.maximum(s, 1e-12)), grid, h)
    out[big] = np.log2(s[big] * math.sqrt(2 * math.pi * math.e))  # the continuous limit
    return out


def binary_bits(p: float) -> float:
    return 0.0 if p <= 0 or p >= 1 else float(-(p * math.log2(p) + (1 - p) * math.log2(1 - p)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds (default 10)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lidar", choices=["points", "packets"], default="points",
                    help="the LiDAR topic recorded: PointCloud2 (default) or the VLP-32C's packets")
    args = ap.parse_args(argv)
    packets = args.lidar == "packets"

    from rosbags.highlevel import AnyReader

    from sim.camera import DepthNoise, hardware
    from sim.episode import Episode
    from sim.scenario import load_scenario
    from stack.messages import CameraFrame, LidarScan
    from testbed.bags import topics as T
    from testbed.record import record_episode

    hw = hardware()
    dn = DepthNoise.from_hardware()
    col_bits = colour_bits_table(hw["d435i"]["read_noise"])
    drop_bits = binary_bits(dn.dropout)
    range_sigma = float(hw["velodyne"]["range_noise"])

    sc = load_scenario(None)
    sc.sensors.noise = False  # the signals; the noise's entropy is computed from the models
    sc.sensors.lidar_packets = packets
    floor = Counter()
    n_msgs = Counter()
    with Episode(sc, seed=args.seed, duration=args.duration, segmentation=False) as ep:
        light = ep.light
        scale = np.clip(np.rint(np.arange(256) * float(light)), 0, 255).astype(np.uint8)
        for msg in ep.frames():
            if isinstance(msg, CameraFrame):
                # colour: the exposure-scaled signal, then the noise table's entropy per value
                sig = msg.rgb if light == 1.0 else np.take(scale, msg.rgb)
                floor["colour"] += float(np.bincount(sig.reshape(-1), minlength=256) @ col_bits) / 8
                z = msg.depth_m[msg.depth_m > 0].astype(float)
                sigma_mm = 1000.0 * dn.sigma(z)
                floor["depth"] += (float(rounded_gaussian_bits(sigma_mm).sum()) + drop_bits * msg.depth_m.size) / 8
                n_msgs["colour"] += 1
                n_msgs["depth"] += 1
            elif isinstance(msg, LidarScan) and packets:
                from stack.velodyne import VLP32C

                sigma_steps = np.full(len(msg.points), range_sigma / VLP32C.distance_resolution)
                floor["lidar"] += float(rounded_gaussian_bits(sigma_steps).sum()) / 8
                n_msgs["lidar"] += 1
            elif isinstance(msg, LidarScan):
                pts = np.abs(msg.points.astype(np.float32))
                ulp = np.spacing(pts.max(axis=1))
                floor["lidar"] += float(np.log2(range_sigma * math.sqrt(2 * math.pi * math.e) / ulp).sum()) / 8
                n_msgs["lidar"] += 1
        sim_s = ep.sim_seconds

    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "bag"
        rec = record_episode(None, bag, seed=args.seed, duration=args.duration, lidar=args.lidar)
        written = Counter()
        counts = Counter()
        with AnyReader([bag]) as reader:
            for conn, _, data in reader.messages():
                written[conn.topic] += len(data)
                counts[conn.topic] += 1
        bag_bytes = rec["bytes"]
    topic_of = {"colour": next(t for t in written if t.startswith(T.RGB) and "info" not in t),
                "depth": next(t for t in written if t.startswith(T.DEPTH) and "info" not in t), "lidar": T.LIDAR_PACKETS if packets else T.LIDAR}
    per60 = 60.0 / sim_s
    print(f"default episode, seed {args.seed}, {sim_s:g} s; noise floor from the sensor models; written = our "
          f"recorder's message bytes (before the MCAP chunks' zstd); the whole bag: {bag_bytes / 1e6:.0f} MB "
          f"({bag_bytes * per60 / 1e6:.0f} MB per 60 s)\n")
    print("| topic | messages | written, KB per message | noise floor, KB per message | written / floor | "
          "written, MB per 60 s | floor, MB per 60 s |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    tot_w = tot_f = 0.0
    for key in ("colour", "depth", "lidar"):
        topic = topic_of[key]
        w = written[topic] / max(1, counts[topic])
        f = floor[key] / max(1, n_msgs[key])
        tot_w += written[topic] * per60
        tot_f += floor[key] * per60
        print(f"| {topic} | {counts[topic]} | {w / 1e3:.0f} | {f / 1e3:.0f} | {w / f:.2f} | "
              f"{written[topic] * per60 / 1e6:.0f} | {floor[key] * per60 / 1e6:.0f} |")
    print(f"| **camera and LiDAR** | | | | {tot_w / tot_f:.2f} | **{tot_w / 1e6:.0f}** | **{tot_f / 1e6:.0f}** |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
