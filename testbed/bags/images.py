"""Lossless compressed camera topics, as ``image_transport`` publishes them from a RealSense.

- colour: ``sensor_msgs/CompressedImage`` with ``format = "rgb8; png compressed bgr8"`` (the
  ``compressed`` plugin's PNG mode): the PNG holds BGR pixels;
- depth: ``format = "16UC1; compressedDepth png"`` (the ``compressed_depth`` plugin): the data is a
  12-byte ``ConfigHeader`` (int32 compression format, 1 = PNG; two float32 depth quantisation
  parameters, unused for 16-bit depth) followed by a 16-bit single-channel PNG of the millimetres.

Both are lossless, so a bag replays exactly as its raw twin. Topic names follow ``image_transport``:
the raw topic plus ``/compressed`` or ``/compressedDepth``.
"""
from __future__ import annotations

import struct
from typing import Any

import numpy as np

COMPRESSED = "sensor_msgs/msg/CompressedImage"
RGB_FORMAT = "rgb8; png compressed bgr8"
DEPTH_FORMAT = "16UC1; compressedDepth png"
PNG_LEVEL = 1  # zlib level: the fastest; higher levels shrink depth a few per cent at several times the CPU
_HEADER = struct.Struct("<iff")  # compressed_depth_image_transport::ConfigHeader
_FORMAT_PNG = 1  # compressionFormat: INV_DEPTH = 0, PNG = 1, RVL = 2
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def compressed_topic(raw_topic: str, depth: bool) -> str:
    return raw_topic.rstrip("/") + ("/compressedDepth" if depth else "/compressed")


def _encode_png(pixels: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL])
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {pixels.shape}")
    return buf.tobytes()


def rgb_png(d, stamp_ns: int, frame_id: str, rgb: np.ndarray) -> Any:
    """A CompressedImage of (H, W, 3) uint8 RGB pixels (PNG of BGR, as image_transport writes it)."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"colour image must be (H, W, 3) uint8, got {a.shape} {a.dtype}")
    import cv2

    data = _encode_png(cv2.cvtColor(a, cv2.COLOR_RGB2BGR))
    return d.make(COMPRESSED, header=d.header(stamp_ns, frame_id), format=RGB_FORMAT,
                  data=np.frombuffer(data, dtype=np.uint8))


def depth_png(d, stamp_ns: int, frame_id: str, depth_mm: np.ndarray) -> Any:
    """A compressedDepth CompressedImage of (H, W) uint16 millimetres: ConfigHeader + 16-bit PNG."""
    a = np.asarray(depth_mm)
    if a.dtype != np.uint16 or a.ndim != 2:
        raise ValueError(f"depth image must be (H, W) uint16 millimetres, got {a.shape} {a.dtype}")
    data = _HEADER.pack(_FORMAT_PNG, 0.0, 0.0) + _encode_png(np.ascontiguousarray(a))
    return d.make(COMPRESSED, header=d.header(stamp_ns, frame_id), format=DEPTH_FORMAT,
                  data=np.frombuffer(data, dtype=np.uint8))


def is_compressed_depth(msg: Any) -> bool:
    return "compresseddepth" in str(getattr(msg, "format", "")).replace(" ", "").lower()


def decode_depth_mm(msg: Any) -> np.ndarray:
    """(H, W) uint16 millimetres of a ``16UC1; compressedDepth png`` CompressedImage. Raises
    ValueError naming what is wrong (another depth encoding, RVL, a short or broken payload)."""
    import cv2

    fmt = str(getattr(msg, "format", ""))
    head = fmt.split(";")[0].strip()
    if head not in ("16UC1", "mono16"):
        raise ValueError(f"compressedDepth format {fmt!r}: only 16-bit depth (16UC1) is read")
    raw = np.asarray(msg.data, dtype=np.uint8).tobytes()
    if raw[:8] == _PNG_MAGIC:  # some writers leave the header out
        png = raw
    else:
        if len(raw) < _HEADER.size:
            raise ValueError(f"compressedDepth data of {len(raw)} bytes is shorter than its 12-byte header")
        kind, _, _ = _HEADER.unpack_from(raw)
        if kind != _FORMAT_PNG:
            raise ValueError(f"compressedDepth compression {kind} (1 = PNG expected; RVL is not read)")
        png = raw[_HEADER.size:]
    out = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if out is None or out.dtype != np.uint16 or out.ndim != 2:
        raise ValueError(f"compressedDepth data is not a 16-bit single-channel PNG (format {fmt!r})")
    return out


def decode_rgb(msg: Any) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a colour CompressedImage (PNG or JPEG; BGR unless the format says rgb)."""
    import cv2

    buf = np.asarray(msg.data, dtype=np.uint8)
    fmt = str(getattr(msg, "format", "")).replace(" ", "").lower()
    swap = not ("compressedrgb8" in fmt)  # image_transport stores colour PNGs/JPEGs as bgr8 by default
    # an OpenCV with IMREAD_COLOR_RGB swaps to RGB as it decodes (the same pixels, no second pass)
    direct = swap and hasattr(cv2, "IMREAD_COLOR_RGB")
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR_RGB if direct else cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"could not decode compressed image (format {msg.format!r})")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if swap and not direct else img
