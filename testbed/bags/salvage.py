"""Recover the complete messages of a truncated or damaged ROS 1 bag or MCAP file.

A recorder that dies (power cut, full disk, killed process) leaves a ROS 1 bag
without its index and an MCAP file without its summary and footer. Both formats
store messages in self-describing chunks written one after another, so the chunks
before the damage can still be read by walking the records from the start. This
module does that walk (bounded: every step advances through the file, and record
sizes are checked against the file size) and serves the messages of the intact
chunks in time order, opening only the chunks it needs. SQLite storage has no
such structure once its pages are cut; it is not salvaged.
"""
from __future__ import annotations

import heapq
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Collection, Iterator

from lz4.frame import decompress as lz4_decompress
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.msg import normalize_msgtype

from stack.errors import DopeSlamError

try:  # Python 3.14 ships zstd; before that rosbags depends on the backport
    from compression import zstd  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the interpreter
    from backports import zstd  # type: ignore[import-not-found,no-redef]

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
_IDL_SEP = "=" * 80 + "\n"


class SalvageError(DopeSlamError):
    """The file is not a bag this module can walk (wrong magic, unsupported compression)."""


@dataclass
class _Chunk:
    """Where one chunk's bytes lie and which messages it holds (times and offsets, no data)."""

    pos: int  # file offset of the (compressed) chunk data
    length: int
    compression: str
    uncompressed_size: int
    entries: list[tuple[int, int, int, int]]  # (time ns, connection id, offset, length) sorted by time
    start: int = 0
    topics: set[str] = field(default_factory=set)


@dataclass
class SalvageReport:
    """What the walk found: how far the intact part reaches and what was skipped."""

    path: Path
    file_size: int
    good_bytes: int  # the file is intact up to here
    messages: int
    chunks: int
    notes: list[str] = field(default_factory=list)
    # damaged chunks passed over: byte, reason, and from the index records that follow a chunk (when
    # intact) the bag-time span and the message count per topic that were lost with it
    skipped: list[dict] = field(default_factory=list)

    def summary(self) -> str:
        pct = 100.0 * self.good_bytes / max(self.file_size, 1)
        text = (f"recovered {self.messages} complete messages from {self.chunks} chunks "
                f"(intact up to byte {self.good_bytes:,} of {self.file_size:,}, {pct:.0f}%)")
        return text + ("; " + "; ".join(self.notes) if self.notes else "")


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression in ("", "none"):
        raw = data
    elif compression == "lz4":
        raw = lz4_decompress(data)
    elif compression == "zstd":
        raw = zstd.decompress(data)
    elif compression == "bz2":
        import bz2

        raw = bz2.decompress(data)
    else:
        raise SalvageError(f"chunk compression {compression!r} is not supported")
    if len(raw) != size:
        raise ValueError(f"chunk decompressed to {len(raw)} bytes, header says {size}")
    return raw


class SalvagedBag:
    """Messages of the intact chunks of one or more files, in time order.

    ``topics`` maps topic -> message type; ``messages(topics)`` yields
    (topic, time ns, message type, raw bytes) and ``deserialize`` decodes them.
    """

    def __init__(self, paths: list[Path]):
        self.paths = paths
        self.typestore = get_typestore(Stores.EMPTY)
        self.ros1 = paths[0].suffix == ".bag"
        self._conns: dict[tuple[int, int], tuple[str, str]] = {}  # (file, conn id) -> (topic, type)
        self._chunks: list[tuple[int, _Chunk]] = []
        self.reports: list[SalvageReport] = []
        typedefs: dict = {}
        for index, path in enumerate(paths):
            with path.open("rb") as f:
                if self.ros1:
                    report = self._walk_ros1(index, f, path, typedefs)
                else:
                    report = self._walk_mcap(index, f, path, typedefs)
            self.reports.append(report)
        self.typestore.register(typedefs)
        # messages whose connection was defined only in a damaged chunk are kept when the summary
        # (MCAP) or the index section (ROS 1) defines it again; the others cannot be decoded
        kept: list[tuple[int, _Chunk]] = []
        for report in self.reports:
            report.chunks = report.messages = 0
        for file_index, chunk in self._chunks:
            chunk.entries = [e for e in chunk.entries if (file_index, e[1]) in self._conns]
            if chunk.entries:
                chunk.start = chunk.entries[0][0]
                kept.append((file_index, chunk))
                self.reports[file_index].chunks += 1
                self.reports[file_index].messages += len(chunk.entries)
        self._chunks = kept
        for index, report in enumerate(self.reports):
            for skipped in report.skipped:
                by_id = skipped.pop("_by_channel")
                stamps = skipped.pop("_stamps")
                if stamps:
                    skipped["start_s"], skipped["end_s"] = min(stamps) * 1e-9, max(stamps) * 1e-9
                messages: dict[str, int] = {}
                for cid, n in by_id.items():
                    topic = self._conns.get((index, cid), (f"channel {cid}", ""))[0]
                    messages[topic] = messages.get(topic, 0) + n
                skipped["messages"] = dict(sorted(messages.items()))
        self.topics: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        for (file_index, cid), (topic, msgtype) in self._conns.items():
            self.topics[topic] = msgtype
        for file_index, chunk in self._chunks:
            for _, cid, _, _ in chunk.entries:
                topic = self._conns[(file_index, cid)][0]
                self.counts[topic] = self.counts.get(topic, 0) + 1
                chunk.topics.add(topic)

    @property
    def message_count(self) -> int:
        return sum(r.messages for r in self.reports)

    def summary(self) -> str:
        return "; ".join(f"{r.path.name}: {r.summary()}" for r in self.reports)

    @property
    def skipped_chunks(self) -> list[dict]:
        """The damaged chunks passed over, in file order: ``file``, ``byte``, ``reason``, and where
        the bag's index records say it, ``start_s``/``end_s`` (bag time) and ``messages`` per topic."""
        return [dict(c) for r in self.reports for c in r.skipped]

    def deserialize(self, raw: bytes, msgtype: str) -> object:
        if self.ros1:
            return self.typestore.deserialize_ros1(raw, msgtype)
        return self.typestore.deserialize_cdr(raw, msgtype)

    def messages(self, topics: Collection[str]) -> Iterator[tuple[str, int, str, bytes]]:
        """Merge the chunks lazily: a chunk is opened once the heap's head is later than its start."""
        wanted = set(topics)
        chunks = sorted(((c.start, i, fi, c) for i, (fi, c) in enumerate(self._chunks) if c.topics & wanted),
                        key=lambda x: (x[0], x[1]))
        heap: list[tuple[int, int, str, str, bytes]] = []
        seq = 0
        k = 0
        while k < len(chunks) or heap:
            while k < len(chunks) and (not heap or chunks[k][0] <= heap[0][0]):
                _, _, file_index, chunk = chunks[k]
                k += 1
                for t, topic, msgtype, raw in self._load(file_index, chunk, wanted):
                    heapq.heappush(heap, (t, seq, topic, msgtype, raw))
                    seq += 1
            if heap:
                t, _, topic, msgtype, raw = heapq.heappop(heap)
                yield topic, t, msgtype, raw

    def _load(self, file_index: int, chunk: _Chunk, wanted: set[str]) -> list[tuple[int, str, str, bytes]]:
        with self.paths[file_index].open("rb") as f:
            f.seek(chunk.pos)
            data = _decompress(f.read(chunk.length), chunk.compression, chunk.uncompressed_size)
        out = []
        for t, cid, offset, length in chunk.entries:
            topic, msgtype = self._conns[(file_index, cid)]
            if topic in wanted:
                out.append((t, topic, msgtype, data[offset:offset + length]))
        return out

    # --- ROS 1 -------------------------------------------------------------------------
    def _walk_ros1(self, file_index: int, f: BinaryIO, path: Path, typedefs: dict) -> SalvageReport:
        size = path.stat().st_size
        if f.read(len(ROS1_MAGIC)) != ROS1_MAGIC:
            raise SalvageError("not a ROS 1 bag (version 2.0 magic missing)")
        report = SalvageReport(path, size, len(ROS1_MAGIC), 0, 0)
        pos = len(ROS1_MAGIC)
        damaged: dict | None = None  # the last chunk, when it was skipped: its index records follow it
        while pos < size:
            record = _read_ros1_record(f, pos, size)
            if isinstance(record, str):
                report.notes.append(f"{record} at byte {pos:,}")
                break
            header, data_pos, data_len = record
            op = header.get("op", b"\x00")[0]
            if op != 0x04 and op != 0x05:
                damaged = None
            if op == 0x04 and damaged is not None:  # index data after a damaged chunk: what it held
                try:
                    cid, count = struct.unpack("<I", header["conn"])[0], struct.unpack("<I", header["count"])[0]
                    f.seek(data_pos)
                    index = f.read(min(data_len, 12 * count))
                    damaged["_by_channel"][cid] = damaged["_by_channel"].get(cid, 0) + count
                    damaged["_stamps"].extend(sec * 10**9 + nsec for sec, nsec, _ in struct.iter_unpack("<III", index[:len(index) // 12 * 12]))
                except (KeyError, struct.error):
                    pass
            if op == 0x07:  # connection record (in the index section)
                f.seek(data_pos)
                self._ros1_connection(file_index, header, f.read(data_len), typedefs)
            elif op == 0x05:  # chunk
                try:
                    compression = header["compression"].decode()
                    usize = struct.unpack("<I", header["size"])[0]
                    f.seek(data_pos)
                    raw = _decompress(f.read(data_len), compression, usize)
                    entries = self._ros1_chunk_entries(file_index, raw, typedefs)
                except (KeyError, ValueError, RuntimeError, struct.error, SalvageError) as exc:
                    report.notes.append(f"skipped a damaged chunk at byte {pos:,} ({exc})")
                    report.skipped.append(_skipped(path, pos, exc))
                    entries = []
                    damaged = report.skipped[-1]
                else:
                    damaged = None
                if entries:
                    entries.sort()
                    self._chunks.append((file_index, _Chunk(data_pos, data_len, compression, usize,
                                                            entries, start=entries[0][0])))
                    report.chunks += 1
                    report.messages += len(entries)
            pos = data_pos + data_len
            report.good_bytes = pos
        f.seek(pos)
        return report

    def _ros1_connection(self, file_index: int, header: dict[str, bytes], data: bytes, typedefs: dict) -> None:
        cid = struct.unpack("<I", header["conn"])[0]
        fields = _parse_ros1_header(data)
        msgtype = normalize_msgtype(fields["type"].decode())
        self._conns[(file_index, cid)] = (fields.get("topic", header.get("topic", b"")).decode(), msgtype)
        typedefs.update(get_types_from_msg(fields["message_definition"].decode(), msgtype))

    def _ros1_chunk_entries(self, file_index: int, raw: bytes, typedefs: dict) -> list[tuple[int, int, int, int]]:
        entries = []
        pos = 0
        while pos + 8 <= len(raw):
            (hlen,) = struct.unpack_from("<I", raw, pos)
            if pos + 4 + hlen + 4 > len(raw):
                break
            header = _parse_ros1_header(raw[pos + 4:pos + 4 + hlen])
            (dlen,) = struct.unpack_from("<I", raw, pos + 4 + hlen)
            data_pos = pos + 8 + hlen
            if data_pos + dlen > len(raw):
                break
            op = header.get("op", b"\x00")[0]
            if op == 0x07:
                self._ros1_connection(file_index, header, raw[data_pos:data_pos + dlen], typedefs)
            elif op == 0x02:
                cid = struct.unpack("<I", header["conn"])[0]
                sec, nsec = struct.unpack("<II", header["time"])
                entries.append((sec * 10**9 + nsec, cid, data_pos, dlen))  # connection known later, maybe
            pos = data_pos + dlen
        return entries

    # --- MCAP --------------------------------------------------------------------------
    def _walk_mcap(self, file_index: int, f: BinaryIO, path: Path, typedefs: dict) -> SalvageReport:
        size = path.stat().st_size
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise SalvageError("not an MCAP file (magic missing)")
        report = SalvageReport(path, size, len(MCAP_MAGIC), 0, 0)
        pos = len(MCAP_MAGIC)
        schemas: dict[int, tuple[str, str, str]] = {}
        damaged: dict | None = None  # the last chunk, when it was skipped: its message indexes follow it
        while pos < size:
            head = f.read(9)
            if len(head) < 9:
                report.notes.append(f"file ends inside a record header at byte {pos:,} (truncated)")
                break
            op, length = head[0], struct.unpack_from("<Q", head, 1)[0]
            if pos + 9 + length > size:
                report.notes.append(f"file ends inside a record at byte {pos:,} (truncated)")
                break
            if op == 0x02:  # footer: the rest is the summary
                report.good_bytes = size
                break
            if op == 0x06:
                body = f.read(length)
                try:
                    entries, chunk = self._mcap_chunk(file_index, body, pos + 9, schemas, typedefs)
                except (ValueError, RuntimeError, struct.error, SalvageError, zstd.ZstdError) as exc:
                    report.notes.append(f"skipped a damaged chunk at byte {pos:,} ({exc})")
                    report.skipped.append(_skipped(path, pos, exc))
                    damaged = report.skipped[-1]
                    entries, chunk = 0, None
                else:
                    damaged = None
                if chunk is not None:
                    self._chunks.append((file_index, chunk))
                    report.chunks += 1
                    report.messages += entries
            elif op == 0x07 and damaged is not None:  # message index after a damaged chunk: what it held
                body = f.read(length)
                try:
                    cid, n = struct.unpack_from("<HI", body, 0)
                    pairs = [t for t, _ in struct.iter_unpack("<QQ", body[6:6 + n // 16 * 16])]
                    damaged["_by_channel"][cid] = damaged["_by_channel"].get(cid, 0) + len(pairs)
                    damaged["_stamps"].extend(pairs)
                except struct.error:
                    pass
            elif op in (0x03, 0x04, 0x05):
                damaged = None
                body = f.read(length)
                try:
                    entry = self._mcap_record(file_index, op, body, 0, schemas, typedefs)
                except (ValueError, KeyError, struct.error) as exc:  # a damaged definition (e.g. in the summary)
                    report.notes.append(f"skipped a damaged record (op 0x{op:02x}) at byte {pos:,} ({exc})")
                    entry = None
                if entry is not None:  # an unchunked message: a chunk of its own, stored plain
                    t, cid, offset, mlen = entry
                    self._chunks.append((file_index, _Chunk(pos + 9, length, "", length,
                                                            [(t, cid, offset, mlen)], start=t)))
                    report.chunks += 1
                    report.messages += 1
            else:
                damaged = None if op != 0x07 else damaged
                f.seek(length, 1)
            pos += 9 + length
            report.good_bytes = pos
        return report

    def _mcap_chunk(self, file_index: int, body: bytes, body_pos: int, schemas: dict,
                    typedefs: dict) -> tuple[int, _Chunk | None]:
        _start, _end, usize, crc = struct.unpack_from("<QQQI", body, 0)
        (clen,) = struct.unpack_from("<I", body, 28)
        compression = body[32:32 + clen].decode()
        (rlen,) = struct.unpack_from("<Q", body, 32 + clen)
        data_off = 40 + clen
        if data_off + rlen > len(body):
            raise ValueError("chunk records overrun the chunk")
        raw = _decompress(body[data_off:data_off + rlen], compression, usize)
        if crc and zlib.crc32(raw) != crc:
            raise ValueError(f"chunk CRC mismatch: its data is damaged (CRC32 {zlib.crc32(raw):08x}, "
                             f"recorded {crc:08x})")
        entries = []
        pos = 0
        while pos + 9 <= len(raw):
            op, length = raw[pos], struct.unpack_from("<Q", raw, pos + 1)[0]
            if pos + 9 + length > len(raw):
                break
            entry = self._mcap_record(file_index, op, raw[pos + 9:pos + 9 + length], pos + 9, schemas, typedefs)
            if entry is not None:
                entries.append(entry)
            pos += 9 + length
        if not entries:
            return 0, None
        entries.sort()
        return len(entries), _Chunk(body_pos + data_off, rlen, compression, usize, entries, start=entries[0][0])

    def _mcap_record(self, file_index: int, op: int, body: bytes, body_pos: int, schemas: dict,
                     typedefs: dict) -> tuple[int, int, int, int] | None:
        if op == 0x03:  # schema: id, name, encoding, data
            (sid,) = struct.unpack_from("<H", body, 0)
            name, p = _mcap_string(body, 2)
            encoding, p = _mcap_string(body, p)
            (dlen,) = struct.unpack_from("<I", body, p)
            schemas[sid] = (name, encoding, body[p + 4:p + 4 + dlen].decode())
            _register_ros2_schema(schemas[sid], typedefs)
        elif op == 0x04:  # channel: id, schema id, topic, encoding, metadata
            cid, sid = struct.unpack_from("<HH", body, 0)
            topic, _ = _mcap_string(body, 4)
            name = schemas.get(sid, ("", "", ""))[0]
            if name:
                self._conns[(file_index, cid)] = (topic, normalize_msgtype(name))
        elif op == 0x05:  # message: channel, sequence, log time, publish time, data
            cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", body, 0)
            return log_time, cid, body_pos + 22, len(body) - 22  # its channel may come later (the summary)
        return None


def _skipped(path: Path, pos: int, exc: Exception) -> dict:
    return {"file": path.name, "byte": pos, "reason": str(exc), "_by_channel": {}, "_stamps": []}


def _read_ros1_record(f: BinaryIO, pos: int, size: int) -> tuple[dict[str, bytes], int, int] | str:
    """(header, data offset, data length) of the record at ``pos``, or why it cannot be read."""
    f.seek(pos)
    raw = f.read(4)
    if len(raw) < 4:
        return "file ends inside a record (truncated)"
    (hlen,) = struct.unpack("<I", raw)
    if pos + 4 + hlen + 4 > size:
        return "file ends inside a record header (truncated)"
    try:
        header = _parse_ros1_header(f.read(hlen))
    except ValueError as exc:
        return f"unreadable record header ({exc})"
    (dlen,) = struct.unpack("<I", f.read(4))
    data_pos = pos + 8 + hlen
    if data_pos + dlen > size:
        return "file ends inside a record's data (truncated)"
    return header, data_pos, dlen


def _parse_ros1_header(buf: bytes) -> dict[str, bytes]:
    fields: dict[str, bytes] = {}
    i = 0
    while i < len(buf):
        if i + 4 > len(buf):
            raise ValueError("header field length cut off")
        (n,) = struct.unpack_from("<I", buf, i)
        i += 4
        if n > len(buf) - i:
            raise ValueError("header field longer than the header")
        key, sep, value = buf[i:i + n].partition(b"=")
        if not sep:
            raise ValueError("header field without '='")
        fields[key.decode("ascii", "replace")] = value
        i += n
    return fields


def _mcap_string(buf: bytes, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    if pos + 4 + n > len(buf):
        raise ValueError("string overruns its record")
    return buf[pos + 4:pos + 4 + n].decode(), pos + 4 + n


def _register_ros2_schema(schema: tuple[str, str, str], typedefs: dict) -> None:
    name, encoding, text = schema
    if encoding == "ros2msg":
        typedefs.update(get_types_from_msg(text, normalize_msgtype(name)))
    elif encoding == "ros2idl":
        if text.startswith(f"{_IDL_SEP}IDL: "):
            for part in text.split(_IDL_SEP)[1:]:
                typedefs.update(get_types_from_idl(part.split("\n", 1)[1]))
        else:
            typedefs.update(get_types_from_idl(text))

