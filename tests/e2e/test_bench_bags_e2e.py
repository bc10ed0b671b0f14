"""The bag benchmarks run on a tiny episode and print their tables (no timing or size asserted)."""
import importlib.util

import pytest

from helpers import ROOT

pytestmark = pytest.mark.slow


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_bag_floor_prints_the_table(capsys):
    assert _load("bench_bag_floor").main(["--duration", "0.5"]) == 0
    out = capsys.readouterr().out
    for row in ("/camera/color/image_raw/compressed", "compressedDepth", "/velodyne_points", "camera and LiDAR",
                "noise floor"):
        assert row in out, row


def test_bag_floor_with_the_velodynes_packets(capsys):
    assert _load("bench_bag_floor").main(["--duration", "0.5", "--lidar", "packets"]) == 0
    out = capsys.readouterr().out
    assert "/velodyne_packets" in out and "/velodyne_points" not in out


def test_bag_floor_colour_entropy_from_the_model():
    mod = _load("bench_bag_floor")
    bits = mod.colour_bits_table(2.0)
    assert bits.shape == (256,) and 2.0 < bits[128] < 5.0  # sigma ~2.6 DN: about 3.4 bits
    assert bits[128] > bits[10]  # shot noise grows with the signal
    assert mod.rounded_gaussian_bits([1e-3])[0] < 1e-3  # no noise, no information


def test_odometry_replay_prints_the_table(capsys, tmp_path):
    """On a ROS 1 bag file given with ``--bag``: both commands run on it, and its size is the file's."""
    import re

    from testbed.record import record_episode

    bag = tmp_path / "drive.bag"
    record_episode(None, bag, seed=0, duration=2.0)
    assert _load("bench_odometry_replay").main(["--bag", str(bag), "--repeats", "1", "--keep", str(tmp_path / "w")]) == 0
    out = capsys.readouterr().out
    assert "| kiss_icp_pipeline |" in out and "| dopeslam replay --odometry-only |" in out
    assert int(re.search(r"\((\d+) MB\)", out).group(1)) == round(bag.stat().st_size / 1e6)
