"""Lossless compressed camera topics (PNG colour, compressedDepth 16-bit PNG): bit-exact round trips
through real serialisation (a compressed bag replays to the same labels as its raw twin:
``tests/e2e/test_compressed_images_e2e.py``)."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from testbed.bags import images as IM
from testbed.bags.convert import dialect


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


def test_colour_decoding_keeps_channel_order_with_and_without_direct_rgb(monkeypatch):
    """An OpenCV with IMREAD_COLOR_RGB decodes straight to RGB; one without decodes BGR and swaps: the same pixels,
    and a PNG stored as RGB (``compressed rgb8``) is not swapped either way."""
    import cv2

    d = dialect("ros2")
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, (30, 41, 3), dtype=np.uint8)  # an odd width: no row padding assumed
    bgr_msg = IM.rgb_png(d, 1, "cam", rgb)
    ok, png = cv2.imencode(".png", rgb)  # the pixels as written, read back as "rgb8" without a swap
    assert ok
    rgb_msg = d.make(IM.COMPRESSED, header=d.header(1, "cam"), format="rgb8; png compressed rgb8",
                     data=png.reshape(-1))
    for msg in (bgr_msg, rgb_msg):
        out = IM.decode_rgb(msg)
        assert out.flags.c_contiguous and np.array_equal(out, rgb)
    if hasattr(cv2, "IMREAD_COLOR_RGB"):
        monkeypatch.delattr(cv2, "IMREAD_COLOR_RGB")  # an older OpenCV
        for msg in (bgr_msg, rgb_msg):
            out = IM.decode_rgb(msg)
            assert out.flags.c_contiguous and np.array_equal(out, rgb)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8"])
def test_raw_colour_encodings_become_the_same_rgb_pixels(encoding):
    from testbed.bags.convert import colour_to_rgb

    rng = np.random.default_rng(3)
    rgba = rng.integers(0, 256, (7, 9, 4), dtype=np.uint8)
    pixels = {"rgb8": rgba[:, :, :3], "bgr8": rgba[:, :, 2::-1], "rgba8": rgba, "bgra8": rgba[:, :, [2, 1, 0, 3]],
              "mono8": rgba[:, :, 0]}[encoding]
    want = np.repeat(rgba[:, :, :1], 3, axis=2) if encoding == "mono8" else rgba[:, :, :3]
    out = colour_to_rgb(np.ascontiguousarray(pixels), encoding)
    assert out.dtype == np.uint8 and out.shape == (7, 9, 3) and out.flags.c_contiguous
    assert np.array_equal(out, want)
