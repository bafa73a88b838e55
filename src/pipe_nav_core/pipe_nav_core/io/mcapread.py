"""Low-level MCAP reading: a tolerant linear scanner that yields raw message batches.

The scanner walks the data section record by record in file order (which is the recording
order for rosbag2 and for our writer), decompresses each chunk and locates its Message records
-- from the chunk's MessageIndex records when present (fully vectorized), otherwise by a tight
scan of the record headers. With ``workers`` the zstd chunks are decompressed, checked and
located by a thread pool a few chunks ahead (zstandard and zlib's CRC release the GIL), while
what the chunks tell the scanner (channels, schemas, warnings, corrupt counts) is still taken
in by the consumer's thread in file order: the same batches and warnings as without. A batch
is one chunk's worth of messages as numpy arrays (record offsets, channel ids, log times) into
the decompressed chunk buffer, so that payloads can be decoded in bulk. It copes with files
cut anywhere (the readable prefix is used, even the part of a chunk that a streaming
decompressor recovers), with corrupt chunks (skipped, counted) and with files without a
summary section. The summary reader gives cheap counts and time ranges.

The records are parsed here, not with :mod:`mcap.records`, because that tolerance needs it:
strings are decoded with replacement characters and a field that runs past the end of its
record raises ValueError, where ``mcap.records`` raises UnicodeDecodeError on a damaged topic
name and returns a cut-off field short without a word (tests/unit/test_mcapread.py).

MCAP format: https://mcap.dev/spec (little-endian; records are opcode u8, length u64, content).
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections import deque
from collections.abc import Callable, Container, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.errors import McapFormatError

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

_REC = struct.Struct("<BQ")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_LOOSE_BATCH_BYTES = 4 << 20
# chunk compressions worth a worker thread: zstd decompression costs as much as a quarter of
# reading; lz4 and stored chunks are unpacked faster than a thread hand-off pays back
POOLED_COMPRESSIONS = frozenset({"zstd"})
AHEAD_BYTES = 64 << 20  # compressed chunk bytes a pooled scanner reads ahead of its consumer


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
class ChunkIndexRecord:
    message_start_time: int
    message_end_time: int
    chunk_start_offset: int
    chunk_length: int
    message_index_offsets: dict[int, int]
    message_index_length: int
    compression: str
    compressed_size: int
    uncompressed_size: int


@dataclass
class Summary:
    """The summary section: schemas, channels, statistics (may be None) and chunk indexes."""

    schemas: dict[int, SchemaRecord] = field(default_factory=dict)
    channels: dict[int, ChannelRecord] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndexRecord] = field(default_factory=list)
    message_count: int | None = None
    message_start_time: int | None = None
    message_end_time: int | None = None
    channel_message_counts: dict[int, int] | None = None


@dataclass
class MessageBatch:
    """Messages of one chunk (or of a run of un-chunked messages), in file order.

    buf: the decompressed bytes; rec: offset of each Message record (at its opcode) in buf;
    channel: channel id per message; log_time: ns per message. Payload i is
    ``buf[rec[i] + 31 : rec[i] + 31 + size[i]]``.
    """

    buf: NDArray[np.uint8]
    rec: NDArray[np.int64]
    channel: NDArray[np.int64]
    log_time: NDArray[np.int64]
    size: NDArray[np.int64]

    @property
    def payload_start(self) -> NDArray[np.int64]:
        return self.rec + MESSAGE_HEADER_SIZE

    def __len__(self) -> int:
        return len(self.rec)


# ----------------------------------------------------------------------------- primitives


class _Cursor:
    """Reads MCAP primitive types from a bytes object."""

    def __init__(self, data: bytes | memoryview, pos: int = 0) -> None:
        self.data = data
        self.pos = pos

    def u8(self) -> int:
        v = self.data[self.pos]
        self.pos += 1
        return v

    def u16(self) -> int:
        (v,) = _U16.unpack_from(self.data, self.pos)
        self.pos += 2
        return v

    def u32(self) -> int:
        (v,) = _U32.unpack_from(self.data, self.pos)
        self.pos += 4
        return v

    def u64(self) -> int:
        (v,) = _U64.unpack_from(self.data, self.pos)
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

    def u16_u64_map(self) -> dict[int, int]:
        nbytes = self.u32()
        raw = self.raw(nbytes)
        return {k: v for k, v in struct.iter_unpack("<HQ", raw[: nbytes - nbytes % 10])}


def parse_schema(content: bytes | memoryview) -> SchemaRecord:
    c = _Cursor(content)
    sid = c.u16()
    name = c.string()
    enc = c.string()
    data = c.raw(c.u32())
    return SchemaRecord(sid, name, enc, data)


def parse_channel(content: bytes | memoryview) -> ChannelRecord:
    c = _Cursor(content)
    cid = c.u16()
    sid = c.u16()
    topic = c.string()
    enc = c.string()
    meta = c.string_map()
    return ChannelRecord(cid, sid, topic, enc, meta)


def parse_chunk_index(content: bytes | memoryview) -> ChunkIndexRecord:
    c = _Cursor(content)
    start, end, off, length = c.u64(), c.u64(), c.u64(), c.u64()
    mi = c.u16_u64_map()
    mil = c.u64()
    comp = c.string()
    return ChunkIndexRecord(start, end, off, length, mi, mil, comp, c.u64(), c.u64())


def _decompressor(compression: str) -> Callable[[bytes, int], bytes]:
    if compression == "":
        return lambda data, size: bytes(data)
    if compression == "zstd":
        try:
            import zstandard

            return lambda data, size: zstandard.ZstdDecompressor().decompress(
                data, max_output_size=size
            )
        except ImportError:  # pragma: no cover - depends on the environment
            from backports import zstd  # type: ignore[import-not-found]

            return lambda data, size: zstd.decompress(data)
    if compression == "lz4":
        import lz4.frame

        return lambda data, size: lz4.frame.decompress(data)
    raise ValueError(f"unsupported chunk compression {compression!r}")


def _decompress_partial(compression: str, data: bytes) -> bytes:
    """Whatever prefix of a cut-off compressed chunk a streaming decompressor recovers."""
    try:
        if compression == "":
            return bytes(data)
        if compression == "zstd":
            import zstandard

            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.LZ4FrameDecompressor().decompress(data)
    except Exception:
        return b""
    return b""


def scan_message_records(
    data: bytes,
    on_schema: Callable[[SchemaRecord], None] | None = None,
    on_channel: Callable[[ChannelRecord], None] | None = None,
) -> tuple[list[int], bool]:
    """Offsets of the Message records in a chunk's records (Schema and Channel records are
    handed to the callbacks). Returns (offsets, complete); complete is False when the last
    record runs past the end of data."""
    unpack = _REC.unpack_from
    n = len(data)
    pos = 0
    offs: list[int] = []
    append = offs.append
    while pos + 9 <= n:
        op, length = unpack(data, pos)
        nxt = pos + 9 + length
        if nxt > n:
            return offs, False
        if op == OP_MESSAGE:
            append(pos)
        elif op == OP_SCHEMA and on_schema is not None:
            on_schema(parse_schema(memoryview(data)[pos + 9 : nxt]))
        elif op == OP_CHANNEL and on_channel is not None:
            on_channel(parse_channel(memoryview(data)[pos + 9 : nxt]))
        pos = nxt
    return offs, pos == n


def _gather_u(buf: NDArray[np.uint8], pos: NDArray[np.int64], nbytes: int, dt: str) -> NDArray:
    """The ``nbytes``-byte little-endian integers at the byte offsets ``pos`` of buf (as the
    rows of a strided view of buf: one index per value; IndexError past the end)."""
    rows = np.lib.stride_tricks.as_strided(
        buf, shape=(max(len(buf) - nbytes + 1, 0), nbytes), strides=(1, 1), writeable=False
    )
    return rows[pos].view(dt).reshape(len(pos))


def make_batch(buf: NDArray[np.uint8], rec: NDArray[np.int64]) -> MessageBatch:
    """Batch from Message record offsets: reads channel ids, log times and payload sizes."""
    rec = np.asarray(rec, dtype=np.int64)
    if len(rec) == 0:
        z = np.zeros(0, dtype=np.int64)
        return MessageBatch(buf, z, z, z, z)
    length = _gather_u(buf, rec + 1, 8, "<u8").astype(np.int64)
    channel = _gather_u(buf, rec + 9, 2, "<u2").astype(np.int64)
    log_time = _gather_u(buf, rec + 15, 8, "<u8").astype(np.int64)
    return MessageBatch(buf, rec, channel, log_time, length - 22)


def _batch_from_indexes(
    buf: NDArray[np.uint8], indexes: list[bytes], known: Container[int]
) -> MessageBatch | None:
    """Vectorized location of messages from MessageIndex records; None if they don't check
    (or name a channel id not in ``known``)."""
    chans: list[NDArray[np.int64]] = []
    offs: list[NDArray[np.int64]] = []
    for content in indexes:
        if len(content) < 6:
            return None
        cid = _U16.unpack_from(content, 0)[0]
        nbytes = _U32.unpack_from(content, 2)[0]
        if cid not in known or nbytes % 16 or 6 + nbytes > len(content):
            return None
        pairs = np.frombuffer(content, dtype="<u8", count=nbytes // 8, offset=6).reshape(-1, 2)
        offs.append(pairs[:, 1].astype(np.int64))
        chans.append(np.full(len(pairs), cid, dtype=np.int64))
    if not offs:
        return None
    rec = np.concatenate(offs)
    chan = np.concatenate(chans)
    order = np.argsort(rec, kind="stable")
    rec, chan = rec[order], chan[order]
    if len(rec) and (rec[0] < 0 or rec[-1] + MESSAGE_HEADER_SIZE > len(buf)):
        return None
    if len(rec) > 1 and np.any(np.diff(rec) < MESSAGE_HEADER_SIZE):
        return None
    if len(rec) and not np.all(buf[rec] == OP_MESSAGE):
        return None
    batch = make_batch(buf, rec)
    if not np.array_equal(batch.channel, chan):
        return None
    if np.any(batch.size < 0) or np.any(batch.rec + MESSAGE_HEADER_SIZE + batch.size > len(buf)):
        return None
    return batch


# ----------------------------------------------------------------------------- scanner


class McapScanner:
    """Linear, tolerant reader of one MCAP file.

    Usage: ``for batch in McapScanner(path, warn).batches(): ...``; ``schemas`` and
    ``channels`` fill up as records are met (the summary is read first when the file has one,
    so that channels are known even for chunks without inline channel records).
    ``truncated`` tells whether the file ended early or had unreadable parts;
    ``corrupt_messages`` counts messages of chunks that had to be skipped, per channel id
    (when the chunk's message index tells), else under key -1.
    """

    def __init__(self, path: str | os.PathLike[str], warn: Callable[[str], None]) -> None:
        self.path = os.fspath(path)
        self.warn = warn
        self.schemas: dict[int, SchemaRecord] = {}
        self.channels: dict[int, ChannelRecord] = {}
        self.truncated = False
        self.corrupt_messages: dict[int, int] = {}
        self.summary: Summary | None = None
        self.size = os.path.getsize(self.path)
        self._ended = False
        with open(self.path, "rb") as f:
            magic = f.read(8)
        if len(magic) < 8 or magic != MAGIC:
            if self.size == 0:
                raise McapFormatError("empty file")
            raise McapFormatError("not an MCAP file (bad magic)")
        try:
            self.summary = read_summary(self.path)
        except Exception:
            self.summary = None
        if self.summary is not None:
            self.schemas.update(self.summary.schemas)
            self.channels.update(self.summary.channels)

    def _on_schema(self, s: SchemaRecord) -> None:
        self.schemas[s.id] = s

    def _on_channel(self, c: ChannelRecord) -> None:
        self.channels[c.id] = c

    def _count_corrupt(self, indexes: list[bytes]) -> None:
        counted = False
        for content in indexes:
            if len(content) >= 6:
                cid = _U16.unpack_from(content, 0)[0]
                n = _U32.unpack_from(content, 2)[0] // 16
                self.corrupt_messages[cid] = self.corrupt_messages.get(cid, 0) + n
                counted = True
        if not counted:
            self.corrupt_messages[-1] = self.corrupt_messages.get(-1, 0) + 1

    def _finish_chunk(self, u: _Unpacked, indexes: list[bytes], offset: int) -> MessageBatch | None:
        """The batch of a complete Chunk record from what :func:`_unpack` made of it: counts a
        corrupt chunk, takes the indexed batch when the channels its indexes name are known by
        now, else scans the records (taking their Schema and Channel records in)."""
        if u.error is not None:  # corrupt chunk: skip it, keep going
            self.truncated = True
            self.warn(
                f"chunk at byte {offset} is unreadable ({u.error}); its messages were skipped"
            )
            self._count_corrupt(indexes)
            return None
        if indexes and all(
            len(ix) >= 2 and _U16.unpack_from(ix, 0)[0] in self.channels for ix in indexes
        ):
            batch = u.indexed if u.located else _batch_from_indexes(u.buf, indexes, self.channels)
            if batch is not None:
                return batch
        offs, complete = scan_message_records(u.raw, self._on_schema, self._on_channel)
        if not complete:
            self.truncated = True
            self.warn(f"chunk at byte {offset} has a damaged record; the rest of it was skipped")
        return _checked_batch(u.buf, offs)

    def _partial_chunk(self, content: bytes, offset: int) -> MessageBatch | None:
        """Recover what can be read from a Chunk record cut off by the end of the file."""
        try:
            c = _Cursor(content)
            c.u64()
            c.u64()
            c.u64()
            c.u32()
            comp = c.string()
            c.u64()
        except Exception:
            return None
        raw = _decompress_partial(comp, content[c.pos :])
        offs, _ = scan_message_records(raw, self._on_schema, self._on_channel)
        if not offs:
            return None
        self.warn(f"recovered {len(offs)} messages from the chunk cut off at byte {offset}")
        return _checked_batch(np.frombuffer(raw, dtype=np.uint8), offs)

    def batches(self, workers: int = 0) -> Iterator[MessageBatch]:
        """Message batches in file order.

        ``workers`` > 0: that many threads decompress and CRC-check the chunks compressed
        the :data:`POOLED_COMPRESSIONS` way and locate their messages from their message
        indexes (zstandard and zlib's CRC release the GIL), at most ``2 * workers`` chunks
        (and :data:`AHEAD_BYTES` of compressed data) ahead of the consumer; other chunks are
        unpacked in this thread. Everything that touches the scanner (schemas, channels,
        record scans, warnings, counts of corrupt chunks) still happens in this thread,
        record by record in file order, so the batches, warnings and counts are exactly those
        of ``workers=0``.
        """
        self._ended = False
        if workers <= 0:
            for item in self._items():
                batch = self._settle(item, None)
                if batch is not None and len(batch):
                    yield batch
        else:
            yield from self._pipelined(workers)
        if not self._ended:
            self.truncated = True
            self.warn(
                f"file ends at byte {self.size} before the end of its data section "
                "(truncated recording?); everything before that point was read"
            )

    def _settle(self, item: _Item, u: _Unpacked | None) -> MessageBatch | None:
        """Take one record (or run of records) of the data section in: its batch, if any."""
        kind = item[0]
        if kind == "chunk":
            _, content, indexes, offset = item
            if u is None:
                u = _unpack(content, indexes, False)
            return self._finish_chunk(u, indexes, offset)
        if kind == "batch":
            return item[1]
        if kind == "partial":
            return self._partial_chunk(item[1], item[2])
        if kind == "schema":
            self._on_schema(parse_schema(item[1]))
        else:
            self._on_channel(parse_channel(item[1]))
        return None

    def _pipelined(self, workers: int) -> Iterator[MessageBatch]:
        """:meth:`batches` with the chunks unpacked by a pool of ``workers`` threads."""
        items = self._items()
        queue: deque[tuple[_Item, Future[_Unpacked] | None]] = deque()
        in_flight = 0
        in_flight_bytes = 0
        failure: Exception | None = None
        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mcap-chunk")
        try:
            while True:
                try:
                    item = next(items)
                except StopIteration:
                    break
                except Exception as exc:  # raised after the batches before it, as serially
                    failure = exc
                    break
                fut: Future[_Unpacked] | None = None
                if item[0] == "chunk" and _compression(item[1]) in POOLED_COMPRESSIONS:
                    fut = pool.submit(_unpack, item[1], item[2], True)
                    in_flight += 1
                    in_flight_bytes += len(item[1])
                queue.append((item, fut))
                while queue and (in_flight > 2 * workers or in_flight_bytes > AHEAD_BYTES):
                    head, fut = queue.popleft()
                    if fut is not None:
                        in_flight -= 1
                        in_flight_bytes -= len(head[1])
                    batch = self._settle(head, None if fut is None else fut.result())
                    if batch is not None and len(batch):
                        yield batch
            while queue:
                head, fut = queue.popleft()
                batch = self._settle(head, None if fut is None else fut.result())
                if batch is not None and len(batch):
                    yield batch
            if failure is not None:
                raise failure
        finally:
            items.close()
            for _, fut in queue:
                if fut is not None:
                    fut.cancel()
            pool.shutdown(wait=True)

    def _items(self) -> Iterator[_Item]:
        """The data section as items in file order: ("chunk", content, message indexes,
        offset) for a complete Chunk record, ("batch", MessageBatch) for a run of un-chunked
        Message records, ("partial", content, offset) for a Chunk record cut off by the end of
        the file, ("schema" | "channel", content) for those records outside chunks. Sets
        ``_ended`` when the data section ends properly."""
        with open(self.path, "rb", buffering=0) as raw_f:
            f = io.BufferedReader(raw_f, buffer_size=1 << 20)
            f.seek(8)
            pos = 8
            size = self.size
            pending: tuple[bytes, int] | None = None
            indexes: list[bytes] = []
            loose = bytearray()
            loose_offs: list[int] = []
            while True:
                hdr = f.read(9)
                if len(hdr) < 9:
                    break
                op, length = _REC.unpack(hdr)
                if op == OP_MESSAGE_INDEX and pending is not None and pos + 9 + length <= size:
                    indexes.append(f.read(length))
                    pos += 9 + length
                    continue
                if pending is not None:
                    yield ("chunk", pending[0], indexes, pending[1])
                    pending, indexes = None, []
                if op in (OP_DATA_END, OP_FOOTER):
                    self._ended = True
                    break
                if op == 0 or pos + 9 + length > size:
                    # cut off (or garbage where a record should start)
                    if op == OP_CHUNK and length > 0:
                        if loose_offs:
                            yield ("batch", _loose_batch(loose, loose_offs))
                            loose, loose_offs = bytearray(), []
                        yield ("partial", f.read(size - pos - 9), pos)
                    break
                if op in (OP_CHUNK, OP_MESSAGE, OP_SCHEMA, OP_CHANNEL):
                    content = f.read(length)
                    if len(content) < length:
                        break
                    if op == OP_CHUNK:
                        if loose_offs:
                            yield ("batch", _loose_batch(loose, loose_offs))
                            loose, loose_offs = bytearray(), []
                        pending = (content, pos)
                    elif op == OP_MESSAGE:
                        loose_offs.append(len(loose))
                        loose += hdr
                        loose += content
                        if len(loose) > _LOOSE_BATCH_BYTES:
                            yield ("batch", _loose_batch(loose, loose_offs))
                            loose, loose_offs = bytearray(), []
                    else:
                        yield ("schema" if op == OP_SCHEMA else "channel", content)
                else:
                    f.seek(length, io.SEEK_CUR)
                pos += 9 + length
            if pending is not None:
                yield ("chunk", pending[0], indexes, pending[1])
            if loose_offs:
                yield ("batch", _loose_batch(loose, loose_offs))


# One item of the data section (see McapScanner._items).
_Item = tuple[Any, ...]


@dataclass
class _Unpacked:
    """What :func:`_unpack` made of one complete Chunk record, without touching a scanner.

    error: why the chunk is unreadable (nothing else is set then); raw, buf: its
    decompressed records (bytes and a uint8 view); located: the MessageIndex records were
    tried, giving ``indexed`` (None when they do not check).
    """

    error: Exception | None = None
    raw: bytes = b""
    buf: NDArray[np.uint8] = field(default_factory=lambda: np.zeros(0, dtype=np.uint8))
    located: bool = False
    indexed: MessageBatch | None = None


def _compression(content: bytes) -> str | None:
    """The compression a Chunk record's content names (None when its header is unreadable)."""
    if len(content) < 32:
        return None
    n = _U32.unpack_from(content, 28)[0]
    if 32 + n > len(content):
        return None
    return content[32 : 32 + n].decode("utf-8", "replace")


def unpack_chunk(content: bytes) -> bytes:
    """The decompressed records of a complete Chunk record's content. Raises (ValueError, or
    the decompressor's error) for a corrupt chunk: bad header, unknown compression, a frame
    that does not decompress, a size or CRC mismatch."""
    c = _Cursor(content)
    c.u64()
    c.u64()
    usize = c.u64()
    crc = c.u32()
    comp = c.string()
    rlen = c.u64()
    if c.pos + rlen > len(content):
        raise ValueError("records run past the chunk record")
    raw = _decompressor(comp)(content[c.pos : c.pos + rlen], usize)
    if len(raw) != usize:
        raise ValueError(f"size {len(raw)} != {usize}")
    if crc and zlib.crc32(raw) != crc:
        raise ValueError("CRC mismatch")
    return raw


def _unpack(content: bytes, indexes: list[bytes], locate: bool) -> _Unpacked:
    """Decompress and check one Chunk record and, with ``locate``, locate its messages from
    its message indexes as if every channel they name were known (the caller checks the
    names). Safe in any thread: it reads nothing but its arguments."""
    try:
        raw = unpack_chunk(content)
    except Exception as exc:
        return _Unpacked(error=exc)
    out = _Unpacked(raw=raw, buf=np.frombuffer(raw, dtype=np.uint8), located=locate)
    if locate and indexes and all(len(ix) >= 2 for ix in indexes):
        named = {_U16.unpack_from(ix, 0)[0] for ix in indexes}
        out.indexed = _batch_from_indexes(out.buf, indexes, named)
    return out


def _loose_batch(loose: bytearray, offs: list[int]) -> MessageBatch:
    return _checked_batch(np.frombuffer(bytes(loose), np.uint8), offs)


def _checked_batch(buf: NDArray[np.uint8], offs: list[int]) -> MessageBatch:
    batch = make_batch(buf, np.asarray(offs, dtype=np.int64))
    good = (batch.size >= 0) & (batch.rec + MESSAGE_HEADER_SIZE + batch.size <= len(buf))
    if not np.all(good):
        batch = MessageBatch(
            buf, batch.rec[good], batch.channel[good], batch.log_time[good], batch.size[good]
        )
    return batch


# ----------------------------------------------------------------------------- summary


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
        summary_start = _U64.unpack_from(tail, 9)[0]
        if summary_start == 0 or summary_start >= size - 8 - FOOTER_RECORD_SIZE:
            return None
        f.seek(summary_start)
        data = f.read(size - 8 - FOOTER_RECORD_SIZE - summary_start)
    out = Summary()
    pos = 0
    while pos + 9 <= len(data):
        op, length = _REC.unpack_from(data, pos)
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
            out.chunk_indexes.append(parse_chunk_index(content))
        elif op == OP_STATISTICS:
            c = _Cursor(content)
            out.message_count = c.u64()
            c.u16()
            c.u32()
            c.u32()
            c.u32()
            c.u32()
            out.message_start_time = c.u64()
            out.message_end_time = c.u64()
            out.channel_message_counts = c.u16_u64_map()
        pos += 9 + length
    return out


def read_record_at(path: str | os.PathLike[str], offset: int) -> tuple[int, bytes]:
    """(opcode, content) of the record starting at ``offset``."""
    with open(path, "rb") as f:
        f.seek(offset)
        hdr = f.read(9)
        op, length = _REC.unpack(hdr)
        return op, f.read(length)


def chunk_messages(path: str | os.PathLike[str], ci: ChunkIndexRecord) -> MessageBatch | None:
    """Decompress one indexed chunk and locate its messages (used by bag_info)."""
    op, content = read_record_at(path, ci.chunk_start_offset)
    if op != OP_CHUNK:
        return None
    scanner = _ChunkOnly()
    return scanner.decode(content)


class _ChunkOnly:
    def decode(self, content: bytes) -> MessageBatch | None:
        try:
            c = _Cursor(content)
            c.u64()
            c.u64()
            usize = c.u64()
            c.u32()
            comp = c.string()
            rlen = c.u64()
            raw = _decompressor(comp)(content[c.pos : c.pos + rlen], usize)
        except Exception:
            return None
        offs, _ = scan_message_records(raw)
        return _checked_batch(np.frombuffer(raw, dtype=np.uint8), offs)
