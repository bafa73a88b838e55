"""The hot path of MCAP reading: a chunk's records decompressed, checked and its Message
records located as numpy arrays (:class:`MessageBatch`), so that payloads can be decoded in bulk.

Messages are located from the chunk's MessageIndex records when present (fully vectorized),
otherwise by a tight scan of the record headers. Everything here reads nothing but its
arguments, so it is safe in any thread (the scanner's worker threads run :func:`unpack`);
zstandard, lz4 and the CRC release the GIL while they work. The CRC is ISA-L's (python-isal):
zlib's CRC-32, computed some three times faster.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Container
from dataclasses import dataclass, field

import numpy as np
from isal.isal_zlib import crc32
from mcap.records import ChunkIndex
from numpy.typing import NDArray

from pipe_nav_core.io.cdr import gather
from pipe_nav_core.io.mcaprecords import (
    MESSAGE_HEADER_SIZE,
    OP_CHANNEL,
    OP_CHUNK,
    OP_MESSAGE,
    OP_SCHEMA,
    REC,
    U16,
    U32,
    ChannelRecord,
    Cursor,
    SchemaRecord,
    parse_channel,
    parse_schema,
    read_record_at,
)


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


def _decompressor(compression: str) -> Callable[[bytes, int], bytes]:
    """The decompression of a chunk's records (data: bytes or a memoryview, size: bytes when
    decompressed); an uncompressed chunk's records are given as they are (not copied)."""
    if compression == "":
        return lambda data, size: data
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


def decompress_partial(compression: str, data: bytes) -> bytes:
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
    header = REC.unpack_from
    n = len(data)
    pos = 0
    offs: list[int] = []
    append = offs.append
    while pos + 9 <= n:
        op, length = header(data, pos)
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


def _gather_int(buf: NDArray[np.uint8], pos: NDArray[np.int64], nbytes: int, dt: str) -> NDArray:
    """The ``nbytes``-byte little-endian integers at the byte offsets ``pos`` of buf
    (:func:`.cdr.gather`; IndexError past the end)."""
    return gather(buf, pos, nbytes).view(dt).reshape(len(pos))


def make_batch(buf: NDArray[np.uint8], rec: NDArray[np.int64]) -> MessageBatch:
    """Batch from Message record offsets: reads channel ids, log times and payload sizes."""
    rec = np.asarray(rec, dtype=np.int64)
    if len(rec) == 0:
        z = np.zeros(0, dtype=np.int64)
        return MessageBatch(buf, z, z, z, z)
    length = _gather_int(buf, rec + 1, 8, "<u8").astype(np.int64)
    channel = _gather_int(buf, rec + 9, 2, "<u2").astype(np.int64)
    log_time = _gather_int(buf, rec + 15, 8, "<u8").astype(np.int64)
    return MessageBatch(buf, rec, channel, log_time, length - 22)


def batch_from_indexes(
    buf: NDArray[np.uint8], indexes: list[bytes], known: Container[int]
) -> MessageBatch | None:
    """Vectorized location of messages from MessageIndex records; None if they don't check
    (or name a channel id not in ``known``)."""
    chans: list[NDArray[np.int64]] = []
    offs: list[NDArray[np.int64]] = []
    for content in indexes:
        if len(content) < 6:
            return None
        cid = U16.unpack_from(content, 0)[0]
        nbytes = U32.unpack_from(content, 2)[0]
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


@dataclass
class Unpacked:
    """What :func:`unpack` made of one complete Chunk record, without touching a scanner.

    error: why the chunk is unreadable (nothing else is set then); raw, buf: its
    decompressed records (bytes and a uint8 view); located: the MessageIndex records were
    tried, giving ``indexed`` (None when they do not check).
    """

    error: Exception | None = None
    raw: bytes = b""
    buf: NDArray[np.uint8] = field(default_factory=lambda: np.zeros(0, dtype=np.uint8))
    located: bool = False
    indexed: MessageBatch | None = None


def chunk_compression(content: bytes) -> str | None:
    """The compression a Chunk record's content names (None when its header is unreadable)."""
    if len(content) < 32:
        return None
    n = U32.unpack_from(content, 28)[0]
    if 32 + n > len(content):
        return None
    return bytes(content[32 : 32 + n]).decode("utf-8", "replace")


def unpack_chunk(content: bytes) -> bytes:
    """The decompressed records of a complete Chunk record's content. Raises (ValueError, or
    the decompressor's error) for a corrupt chunk: bad header, unknown compression, a frame
    that does not decompress, a size or CRC mismatch."""
    c = Cursor(content)
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
    if crc and crc32(raw) != crc:
        raise ValueError("CRC mismatch")
    return raw


def unpack(content: bytes, indexes: list[bytes], locate: bool) -> Unpacked:
    """Decompress and check one Chunk record and, with ``locate``, locate its messages from
    its message indexes as if every channel they name were known (the caller checks the
    names). Safe in any thread: it reads nothing but its arguments."""
    try:
        raw = unpack_chunk(content)
    except Exception as exc:
        return Unpacked(error=exc)
    out = Unpacked(raw=raw, buf=np.frombuffer(raw, dtype=np.uint8), located=locate)
    if locate and indexes and all(len(ix) >= 2 for ix in indexes):
        named = {U16.unpack_from(ix, 0)[0] for ix in indexes}
        out.indexed = batch_from_indexes(out.buf, indexes, named)
    return out


def loose_batch(loose: bytearray, offs: list[int]) -> MessageBatch:
    return checked_batch(np.frombuffer(bytes(loose), np.uint8), offs)


def checked_batch(buf: NDArray[np.uint8], offs: list[int]) -> MessageBatch:
    batch = make_batch(buf, np.asarray(offs, dtype=np.int64))
    good = (batch.size >= 0) & (batch.rec + MESSAGE_HEADER_SIZE + batch.size <= len(buf))
    if not np.all(good):
        batch = MessageBatch(
            buf, batch.rec[good], batch.channel[good], batch.log_time[good], batch.size[good]
        )
    return batch


def chunk_messages(path: str | os.PathLike[str], ci: ChunkIndex) -> MessageBatch | None:
    """Decompress one indexed chunk and locate its messages (used by bag_info)."""
    op, content = read_record_at(path, ci.chunk_start_offset)
    if op != OP_CHUNK:
        return None
    scanner = _ChunkOnly()
    return scanner.decode(content)


class _ChunkOnly:
    def decode(self, content: bytes) -> MessageBatch | None:
        try:
            c = Cursor(content)
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
        return checked_batch(np.frombuffer(raw, dtype=np.uint8), offs)
