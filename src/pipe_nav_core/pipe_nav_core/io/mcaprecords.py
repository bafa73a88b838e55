"""MCAP records outside the hot path: opcodes, the record types the reader keeps, their parsing
and the summary section.

Schema and Channel records are parsed here, not with :mod:`mcap.records`, because the scanner
meets them in the data section of damaged files and must cope: strings are decoded with
replacement characters and a field that runs past the end of its record raises ValueError,
where ``mcap.records`` raises UnicodeDecodeError on a damaged topic name and returns a cut-off
string field short without a word (tests/unit/test_mcapread.py). The summary's Chunk Index and
Statistics records are only used whole or not at all (a summary that does not parse is no
summary: the scanner reads the data section instead), so ``mcap.records`` parses them. The hot
path (chunks and their messages) is :mod:`pipe_nav_core.io.mcapchunks`; the scanner that walks
a file is :mod:`pipe_nav_core.io.mcapread`.

MCAP format: https://mcap.dev/spec (little-endian; records are opcode u8, length u64, content).
"""

from __future__ import annotations

import io
import os
import struct
from dataclasses import dataclass, field

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.records import ChunkIndex, McapRecord, Statistics

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_ATTACHMENT = 0x09
OP_ATTACHMENT_INDEX = 0x0A
OP_STATISTICS = 0x0B
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F

MESSAGE_HEADER_SIZE = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel, sequence, log, publish
FOOTER_RECORD_SIZE = 1 + 8 + 20

REC = struct.Struct("<BQ")  # a record's opcode and length
U16 = struct.Struct("<H")
U32 = struct.Struct("<I")
U64 = struct.Struct("<Q")


@dataclass
class SchemaRecord:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass
class ChannelRecord:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


@dataclass
class Summary:
    """The summary section: schemas, channels, statistics (may be None) and chunk indexes
    (:class:`mcap.records.ChunkIndex`)."""

    schemas: dict[int, SchemaRecord] = field(default_factory=dict)
    channels: dict[int, ChannelRecord] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndex] = field(default_factory=list)
    message_count: int | None = None
    message_start_time: int | None = None
    message_end_time: int | None = None
    channel_message_counts: dict[int, int] | None = None


class Cursor:
    """Reads MCAP primitive types from a bytes object."""

    def __init__(self, data: bytes | memoryview, pos: int = 0) -> None:
        self.data = data
        self.pos = pos

    def u8(self) -> int:
        v = self.data[self.pos]
        self.pos += 1
        return v

    def u16(self) -> int:
        (v,) = U16.unpack_from(self.data, self.pos)
        self.pos += 2
        return v

    def u32(self) -> int:
        (v,) = U32.unpack_from(self.data, self.pos)
        self.pos += 4
        return v

    def u64(self) -> int:
        (v,) = U64.unpack_from(self.data, self.pos)
        self.pos += 8
        return v

    def raw(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ValueError("field runs past the end of its record")
        v = bytes(self.data[self.pos : self.pos + n])
        self.pos += n
        return v

    def string(self) -> str:
        return self.raw(self.u32()).decode("utf-8", "replace")

    def string_map(self) -> dict[str, str]:
        nbytes = self.u32()
        end = self.pos + nbytes
        out: dict[str, str] = {}
        while self.pos < end:
            k = self.string()
            out[k] = self.string()
        return out


def parse_schema(content: bytes | memoryview) -> SchemaRecord:
    c = Cursor(content)
    sid = c.u16()
    name = c.string()
    enc = c.string()
    data = c.raw(c.u32())
    return SchemaRecord(sid, name, enc, data)


def parse_channel(content: bytes | memoryview) -> ChannelRecord:
    c = Cursor(content)
    cid = c.u16()
    sid = c.u16()
    topic = c.string()
    enc = c.string()
    meta = c.string_map()
    return ChannelRecord(cid, sid, topic, enc, meta)


def parse_whole(kind: type[McapRecord], content: bytes | memoryview) -> McapRecord:
    """A record's content parsed by :mod:`mcap.records` (``kind``: e.g. ChunkIndex);
    ValueError when a field runs past the end of the record or a string is not UTF-8."""
    try:
        return kind.read(ReadDataStream(io.BytesIO(content)))
    except (EndOfFile, struct.error, UnicodeDecodeError) as exc:
        raise ValueError(f"damaged {kind.__name__} record ({exc!r})") from None


def read_summary(path: str | os.PathLike[str]) -> Summary | None:
    """The summary section of an MCAP file, or None when it has none or it is unreadable."""
    size = os.path.getsize(path)
    if size < 8 + FOOTER_RECORD_SIZE + 8:
        return None
    with open(path, "rb") as f:
        f.seek(size - 8 - FOOTER_RECORD_SIZE)
        tail = f.read(8 + FOOTER_RECORD_SIZE)
        if tail[-8:] != MAGIC or tail[0] != OP_FOOTER:
            return None
        summary_start = U64.unpack_from(tail, 9)[0]
        if summary_start == 0 or summary_start >= size - 8 - FOOTER_RECORD_SIZE:
            return None
        f.seek(summary_start)
        data = f.read(size - 8 - FOOTER_RECORD_SIZE - summary_start)
    out = Summary()
    pos = 0
    while pos + 9 <= len(data):
        op, length = REC.unpack_from(data, pos)
        content = memoryview(data)[pos + 9 : pos + 9 + length]
        if len(content) < length:
            break
        if op == OP_SCHEMA:
            s = parse_schema(content)
            out.schemas[s.id] = s
        elif op == OP_CHANNEL:
            ch = parse_channel(content)
            out.channels[ch.id] = ch
        elif op == OP_CHUNK_INDEX:
            out.chunk_indexes.append(parse_whole(ChunkIndex, content))
        elif op == OP_STATISTICS:
            st = parse_whole(Statistics, content)
            out.message_count = st.message_count
            out.message_start_time = st.message_start_time
            out.message_end_time = st.message_end_time
            out.channel_message_counts = st.channel_message_counts
        pos += 9 + length
    return out


def read_record_at(path: str | os.PathLike[str], offset: int) -> tuple[int, bytes]:
    """(opcode, content) of the record starting at ``offset``."""
    with open(path, "rb") as f:
        f.seek(offset)
        hdr = f.read(9)
        op, length = REC.unpack(hdr)
        return op, f.read(length)
