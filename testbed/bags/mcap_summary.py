"""The MCAP footer's ``summary_crc``: the CRC32 of the summary section, the summary offset section and
the footer up to that field (MCAP spec, "Footer"). rosbags writes 0 there ("not computed"), so a
damaged summary (the index a reader trusts to find every chunk) would go unnoticed.

:func:`write_summary_crc` fills the field in once the file is complete; :func:`summary_crc_problem`
checks it on read (None when it matches or was never computed).

Footer layout, the last 37 bytes of the file: op 0x02, u64 record length (20), u64 summary_start,
u64 summary_offset_start, u32 summary_crc, then the 8-byte magic.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

MAGIC = b"\x89MCAP0\r\n"
FOOTER_BYTES = 1 + 8 + 20  # op, length, body
CRC_SPAN_END = FOOTER_BYTES - 4  # the CRC covers the footer up to (not including) its own field


def _footer(f, size: int) -> tuple[int, int, int, int] | None:
    """(footer offset, summary_start, summary_offset_start, summary_crc), or None when the file does
    not end in an MCAP footer and magic (truncated, or not MCAP)."""
    end = FOOTER_BYTES + len(MAGIC)
    if size < len(MAGIC) + end:
        return None
    f.seek(size - end)
    tail = f.read(end)
    if tail[-len(MAGIC):] != MAGIC or tail[0] != 0x02 or struct.unpack_from("<Q", tail, 1)[0] != 20:
        return None
    start, offset_start, crc = struct.unpack_from("<QQI", tail, 9)
    return size - end, start, offset_start, crc


def _summary_crc(f, footer_at: int, summary_start: int) -> int:
    """CRC32 from the summary's start through the footer's ``summary_offset_start`` field."""
    f.seek(summary_start)
    crc, left = 0, footer_at + CRC_SPAN_END - summary_start
    while left > 0:
        block = f.read(min(left, 1 << 20))
        if not block:
            break
        crc = zlib.crc32(block, crc)
        left -= len(block)
    return crc


def _checkable(f, path: Path) -> tuple[int, int, int] | None:
    """(footer offset, summary_start, summary_crc) of a file with a footer and a summary section
    inside it, else None."""
    found = _footer(f, path.stat().st_size)
    if found is None:
        return None
    footer_at, start, _offsets, crc = found
    if start == 0 or not len(MAGIC) <= start <= footer_at:
        return None
    return footer_at, start, crc


def write_summary_crc(path: str | Path) -> bool:
    """Fill in the footer's ``summary_crc`` of a complete MCAP file whose field is still 0; returns
    whether it wrote one (False: no summary section, a CRC already there, or no footer)."""
    path = Path(path)
    with open(path, "r+b") as f:
        found = _checkable(f, path)
        if found is None or found[2] != 0:
            return False
        footer_at, start, _ = found
        value = _summary_crc(f, footer_at, start)
        f.seek(footer_at + CRC_SPAN_END)
        f.write(struct.pack("<I", value))
    return True


def summary_crc_problem(path: str | Path) -> str | None:
    """Why the MCAP file's summary cannot be trusted (a CRC mismatch), or None: it matches, or the
    writer did not compute one, or there is no footer or summary to check (a truncated file: the
    reader's own error says so)."""
    path = Path(path)
    with open(path, "rb") as f:
        found = _checkable(f, path)
        if found is None or found[2] == 0:
            return None
        footer_at, start, crc = found
        got = _summary_crc(f, footer_at, start)
    if got != crc:
        return f"summary CRC mismatch: the summary section is damaged (CRC32 {got:08x}, recorded {crc:08x})"
    return None
