"""Lossless compressed camera topics (PNG colour, compressedDepth 16-bit PNG): bit-exact round trips
through real serialisation, and a compressed bag replays to the same labels as its raw twin."""
from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from testbed.bags import images as IM
from testbed.bags.convert import dialect

sys.path.insert(0, str(Path(__file__).resolve().parent))


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_colour_png_round_trips_bit_for_bit(fmt):
    d = dialect(fmt)
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)  # noise: the hardest case for PNG
    rgb[0, 0] = (255, 0, 0)  # channel order is kept
    raw = d.serialize(IM.rgb_png(d, 123, "camera_color_optical_frame", rgb), IM.COMPRESSED)
    msg = d.deserialize(raw, IM.COMPRESSED)
    assert msg.format == IM.RGB_FORMAT
    out = IM.decode_rgb(msg)
    assert out.dtype == np.uint8 and np.array_equal(out, rgb)


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_depth_compressed_depth_round_trips_bit_for_bit(fmt):
    d = dialect(fmt)
    rng = np.random.default_rng(1)
    mm = rng.integers(0, 65536, (48, 64), dtype=np.uint16)
    mm[0, :3] = (0, 1, 65535)  # no return, the smallest and the largest depth
    msg = d.deserialize(d.serialize(IM.depth_png(d, 5, "cam", mm), IM.COMPRESSED), IM.COMPRESSED)
    assert msg.format == IM.DEPTH_FORMAT and IM.is_compressed_depth(msg)
    data = np.asarray(msg.data, dtype=np.uint8).tobytes()
    assert struct.unpack("<iff", data[:12]) == (1, 0.0, 0.0)  # ConfigHeader: PNG
    assert data[12:20] == b"\x89PNG\r\n\x1a\n"
    out = IM.decode_depth_mm(msg)
    assert out.dtype == np.uint16 and np.array_equal(out, mm)


def test_bad_compressed_depth_is_refused():
    d = dialect("ros2")
    mm = np.zeros((4, 4), np.uint16)
    good = IM.depth_png(d, 0, "cam", mm)
    rvl = d.make(IM.COMPRESSED, header=good.header, format=good.format,
                 data=np.frombuffer(struct.pack("<iff", 2, 0, 0) + b"x" * 8, np.uint8))
    with pytest.raises(ValueError, match="RVL"):
        IM.decode_depth_mm(rvl)
    inv = d.make(IM.COMPRESSED, header=good.header, format="32FC1; compressedDepth", data=good.data)
    with pytest.raises(ValueError, match="16UC1"):
        IM.decode_depth_mm(inv)
    with pytest.raises(ValueError, match="uint16"):
        IM.depth_png(d, 0, "cam", mm.astype(np.float32))


def test_writer_refuses_bad_images_option(tmp_path):
    from testbed.bags import BagWriter
    from testbed.bags.errors import BagWriteError

    with pytest.raises(BagWriteError, match="images"):
        BagWriter(tmp_path / "b", images="jpeg")


@pytest.mark.slow
def test_compressed_and_raw_bags_replay_to_the_same_labels(tmp_path):
    from test_record_replay import oracle_for, short_scenario
    from testbed.bags import BagReader
    from testbed.bags import topics as T
    from testbed.record import record_episode
    from testbed.replay import replay_bag

    out = {}
    for images in ("raw", "compressed"):
        bag = tmp_path / images
        summary = record_episode(short_scenario(), bag, seed=0, duration=4.0, images=images)
        with BagReader(bag) as r:
            assert (r.rgb_topic, r.depth_topic) == ((T.RGB, T.DEPTH) if images == "raw"
                                                    else (T.RGB_COMPRESSED, T.DEPTH_COMPRESSED))
        det = oracle_for(bag)
        rep = replay_bag(bag, tmp_path / f"out_{images}", detector=det, write_outputs=False)
        out[images] = (summary["bytes"], det.seen, rep["labels_summary"])
    assert out["raw"][1] and out["raw"][1] == out["compressed"][1]  # the same pixels, stamps, intrinsics
    for key in ("labelled", "false_labels"):
        assert out["raw"][2][key] == out["compressed"][2][key], key
    raw_l, comp_l = out["raw"][2]["map_labels"], out["compressed"][2]["map_labels"]
    assert raw_l and len(raw_l) == len(comp_l)
    for a, b in zip(raw_l, comp_l):  # same labels; positions to rounding (KISS-ICP's threads sum in any order)
        assert (a["class"], a["object"], a["verdict"], a["observations"]) == \
            (b["class"], b["object"], b["verdict"], b["observations"])
        assert np.allclose(a["label_xyz"], b["label_xyz"], rtol=0, atol=1e-9)
    assert out["compressed"][0] < out["raw"][0]
