"""The MCAP scanner: a tolerant linear reader of one file that yields its messages in batches.

The scanner walks the data section record by record in file order (which is the recording
order for rosbag2 and for our writer) and turns each chunk into a :class:`MessageBatch` (one
chunk's messages as numpy arrays into its decompressed buffer: :mod:`.mcapchunks`). With
``workers`` the chunks are decompressed, CRC-checked and located by a thread pool a few chunks
ahead, while what the chunks tell the scanner (channels, schemas, warnings, corrupt counts) is
still taken in by the consumer's thread in file order: the same batches and warnings as
without. It copes with files cut anywhere (the readable prefix is used, even the part of a
chunk that a streaming decompressor recovers), with corrupt chunks (skipped, counted) and with
files without a summary section (:mod:`.mcaprecords` reads the summary and the records outside
the hot path).

The names of both those modules that other modules use are re-exported here.

MCAP format: https://mcap.dev/spec (little-endian; records are opcode u8, length u64, content).
"""

from __future__ import annotations

import mmap
import os
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from pipe_nav_core.errors import McapFormatError
from pipe_nav_core.io.mcapchunks import (
    MessageBatch,
    Unpacked,
    batch_from_indexes,
    checked_batch,
    chunk_compression,
    chunk_messages,
    decompress_partial,
    loose_batch,
    make_batch,
    scan_message_records,
    unpack,
    unpack_chunk,
)
from pipe_nav_core.io.mcaprecords import (
    MAGIC,
    MESSAGE_HEADER_SIZE,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
    REC,
    U16,
    U32,
    ChannelRecord,
    Cursor,
    SchemaRecord,
    Summary,
    parse_channel,
    parse_schema,
    read_record_at,
    read_summary,
)

__all__ = [
    "AHEAD_BYTES",
    "MAGIC",
    "MESSAGE_HEADER_SIZE",
    "POOLED_COMPRESSIONS",
    "ChannelRecord",
    "McapFormatError",
    "McapScanner",
    "MessageBatch",
    "SchemaRecord",
    "Summary",
    "chunk_messages",
    "make_batch",
    "parse_channel",
    "parse_schema",
    "read_record_at",
    "read_summary",
    "scan_message_records",
    "unpack_chunk",
]

_LOOSE_BATCH_BYTES = 4 << 20
# chunk compressions unpacked by the worker threads: all of them. The decompression (zstd
# costs three times lz4) and the CRC check (as much as lz4) release the GIL, so on a second
# core they are off the consumer's path; the decoding and the checks hold the GIL and stay
# in the consumer's thread (in a worker they would only take turns with it)
POOLED_COMPRESSIONS = frozenset({"zstd", "lz4", ""})
AHEAD_BYTES = 64 << 20  # compressed chunk bytes a pooled scanner reads ahead of its consumer
STREAMED_RECORD_BYTES = 256 << 20  # the longest record read from a stream (chunks: ~1 MiB)
_DRAIN_BYTES = 16 << 20  # bytes per read of what a stream holds after an unreadable record

# ----------------------------------------------------------------------------- scanner


class McapScanner:
    """Linear, tolerant reader of one MCAP file.

    Usage: ``for batch in McapScanner(path, warn).batches(): ...``; ``schemas`` and
    ``channels`` fill up as records are met (the summary is read first when the file has one,
    so that channels are known even for chunks without inline channel records).
    ``truncated`` tells whether the file ended early or had unreadable parts;
    ``corrupt_messages`` counts messages of chunks that had to be skipped, per channel id
    (when the chunk's message index tells), else under key -1. ``stream``: the file's bytes
    read forward instead of mapped (n -> at most n bytes, fewer only at the end), as a
    compressed file decompresses; a stream has no summary read first, and ``size`` counts
    the bytes read.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        warn: Callable[[str], None],
        stream: Callable[[int], bytes] | None = None,
    ) -> None:
        self.path = os.fspath(path)
        self.warn = warn
        self.schemas: dict[int, SchemaRecord] = {}
        self.channels: dict[int, ChannelRecord] = {}
        self.truncated = False
        self.corrupt_messages: dict[int, int] = {}
        self.summary: Summary | None = None
        self._stream = stream
        self._ended = False
        self._map: _MappedFile | None = None
        if stream is None:
            self.size = os.path.getsize(self.path)
            with open(self.path, "rb") as f:
                magic = f.read(8)
        else:  # the file's bytes as they are read (a decompressing stream: no summary)
            magic = stream(8)
            self.size = len(magic)
        if len(magic) < 8 or magic != MAGIC:
            if self.size == 0:
                raise McapFormatError("empty file")
            raise McapFormatError("not an MCAP file (bad magic)")
        if stream is None:
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
                cid = U16.unpack_from(content, 0)[0]
                n = U32.unpack_from(content, 2)[0] // 16
                self.corrupt_messages[cid] = self.corrupt_messages.get(cid, 0) + n
                counted = True
        if not counted:
            self.corrupt_messages[-1] = self.corrupt_messages.get(-1, 0) + 1

    def _finish_chunk(self, u: Unpacked, indexes: list[bytes], offset: int) -> MessageBatch | None:
        """The batch of a complete Chunk record from what :func:`unpack` made of it: counts a
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
            len(ix) >= 2 and U16.unpack_from(ix, 0)[0] in self.channels for ix in indexes
        ):
            batch = u.indexed if u.located else batch_from_indexes(u.buf, indexes, self.channels)
            if batch is not None:
                return batch
        offs, complete = scan_message_records(u.raw, self._on_schema, self._on_channel)
        if not complete:
            self.truncated = True
            self.warn(f"chunk at byte {offset} has a damaged record; the rest of it was skipped")
        return checked_batch(u.buf, offs)

    def _partial_chunk(self, content: bytes, offset: int) -> MessageBatch | None:
        """Recover what can be read from a Chunk record cut off by the end of the file."""
        try:
            c = Cursor(content)
            c.u64()
            c.u64()
            c.u64()
            c.u32()
            comp = c.string()
            c.u64()
        except Exception:
            return None
        raw = decompress_partial(comp, content[c.pos :])
        offs, _ = scan_message_records(raw, self._on_schema, self._on_channel)
        if not offs:
            return None
        self.warn(f"recovered {len(offs)} messages from the chunk cut off at byte {offset}")
        return checked_batch(np.frombuffer(raw, dtype=np.uint8), offs)

    def batches(self, workers: int = 0) -> Iterator[MessageBatch]:
        """Message batches in file order.

        ``workers`` > 0: that many threads decompress and CRC-check the chunks compressed
        the :data:`POOLED_COMPRESSIONS` way and locate their messages from their message
        indexes (zstandard, lz4 and zlib's CRC release the GIL), at most ``2 * workers``
        chunks (and :data:`AHEAD_BYTES` of compressed data) ahead of the consumer; other
        chunks are unpacked in this thread. Everything that touches the scanner (schemas,
        channels, record scans, warnings, counts of corrupt chunks) still happens in this
        thread, record by record in file order, so the batches, warnings and counts are
        exactly those of ``workers=0``.
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
            while self._stream is not None and (rest := self._stream(_DRAIN_BYTES)):
                self.size += len(rest)  # where the streamed file ends
            self.warn(
                f"file ends at byte {self.size} before the end of its data section "
                "(truncated recording?); everything before that point was read"
            )

    def _settle(self, item: _Item, u: Unpacked | None) -> MessageBatch | None:
        """Take one record (or run of records) of the data section in: its batch, if any."""
        kind = item[0]
        if kind == "chunk":
            _, content, indexes, offset = item
            if self._map is not None:  # the records before it: their batches are done with
                self._map.release(offset)
            if u is None:
                u = unpack(content, indexes, False)
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
        queue: deque[tuple[_Item, Future[Unpacked] | None]] = deque()
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
                fut: Future[Unpacked] | None = None
                if item[0] == "chunk" and chunk_compression(item[1]) in POOLED_COMPRESSIONS:
                    fut = pool.submit(unpack, item[1], item[2], True)
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
        ``_ended`` when the data section ends properly. A file's contents are views of the
        mapped file (:class:`_MappedFile`): nothing is copied until a chunk is decompressed."""
        if self._stream is None:
            self._map = _MappedFile(self.path, self.size)
            records = _mapped_records(self._map.view)
        else:
            records = self._streamed_records(self._stream)
        pending: tuple[Any, int] | None = None
        indexes: list[Any] = []
        loose = bytearray()
        loose_offs: list[int] = []
        for op, pos, rec, whole in records:
            if op == OP_MESSAGE_INDEX and pending is not None and whole:
                indexes.append(rec[9:])
                continue
            if pending is not None:
                yield ("chunk", pending[0], indexes, pending[1])
                pending, indexes = None, []
            if op in (OP_DATA_END, OP_FOOTER):
                self._ended = True
                break
            if op == 0 or not whole:  # cut off (or garbage where a record should start)
                if op == OP_CHUNK:
                    if loose_offs:
                        yield ("batch", loose_batch(loose, loose_offs))
                        loose, loose_offs = bytearray(), []
                    yield ("partial", rec[9:], pos)
                break
            if op == OP_CHUNK:
                if loose_offs:
                    yield ("batch", loose_batch(loose, loose_offs))
                    loose, loose_offs = bytearray(), []
                pending = (rec[9:], pos)
            elif op == OP_MESSAGE:
                loose_offs.append(len(loose))
                loose += rec
                if len(loose) > _LOOSE_BATCH_BYTES:
                    yield ("batch", loose_batch(loose, loose_offs))
                    loose, loose_offs = bytearray(), []
            elif op in (OP_SCHEMA, OP_CHANNEL):
                yield ("schema" if op == OP_SCHEMA else "channel", bytes(rec[9:]))
        if pending is not None:
            yield ("chunk", pending[0], indexes, pending[1])
        if loose_offs:
            yield ("batch", loose_batch(loose, loose_offs))

    def _streamed_records(self, read: Callable[[int], bytes]) -> Iterator[_Record]:
        """:func:`_mapped_records` of a file read forward by ``read`` (n -> at most n bytes,
        fewer only at its end); ``size`` counts the bytes read. A record said to be longer
        than STREAMED_RECORD_BYTES (a damaged length, as a rule) is read that far and taken
        as cut off there."""
        while len(head := read(9)) == 9:
            op, length = REC.unpack(head)
            body = read(min(length, STREAMED_RECORD_BYTES)) if op else b""
            pos, self.size = self.size, self.size + 9 + len(body)
            yield op, pos, memoryview(head + body), len(body) == length
            if len(body) < length:
                return
        self.size += len(head)


def _mapped_records(data: memoryview) -> Iterator[_Record]:
    """The records of a mapped MCAP file after its magic: (opcode, offset, the record with its
    opcode and length, whether it is whole); the last one may be cut off by the file's end."""
    size, pos = len(data), 8
    while pos + 9 <= size:
        op, length = REC.unpack_from(data, pos)
        end = pos + 9 + length
        yield op, pos, data[pos : min(end, size)], end <= size
        if end > size:
            return
        pos = end


class _MappedFile:
    """A file's first ``size`` bytes mapped read-only (``view``): the records are read in
    place, not copied out (an uncompressed 10 km bag is 620 MB of chunks: copying them and
    faulting in the copies' fresh pages took 0.3 s of 1.1 s). The pages read count in the
    process's resident memory until :meth:`release` lets go of them (the file's data stay in
    the page cache); where the file cannot be mapped it is read whole."""

    def __init__(self, path: str, size: int) -> None:
        self._mm: mmap.mmap | None = None
        self._released = 0
        with open(path, "rb") as f:
            try:
                self._mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
                whole: bytes | mmap.mmap = self._mm
            except (OSError, ValueError):  # a file system without mmap
                whole = f.read(size)
        self.view = memoryview(whole)[:size]

    def release(self, upto: int) -> None:
        """Take the pages before byte ``upto`` out of the process's resident memory (a read
        of them after maps them in again, from the page cache)."""
        start = self._released
        upto -= upto % mmap.PAGESIZE
        if self._mm is None or upto <= start or not hasattr(self._mm, "madvise"):
            return
        self._mm.madvise(mmap.MADV_DONTNEED, start, upto - start)
        self._released = upto


# One item of the data section (see McapScanner._items).
_Item = tuple[Any, ...]
# One record of an MCAP file: opcode, offset, the record's bytes, whether whole.
_Record = tuple[int, int, Any, bool]
