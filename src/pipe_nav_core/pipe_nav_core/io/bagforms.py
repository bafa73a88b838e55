"""The forms rosbag2 writes a bag in besides plain MCAP files, read as message batches.

- sqlite3 storage (``.db3``, rosbag2's default before Iron): :class:`Db3Scanner` reads its
  ``messages`` table in recording order, the topics the reader asks for only (a camera's
  images in the same bag are not read), through Python's own sqlite3, SQLite concatenating
  each batch's payloads.
- zstd compression of whole files (``compression_mode: file``, ``x.mcap.zstd``):
  :func:`open_scanner` scans an MCAP file as it decompresses (:class:`ZstdStream`), and
  decompresses a sqlite3 file into a temporary one, scans that and removes it; a compressed
  stream cut short gives the part before the cut (a warning says so), which the scanners
  read as they read a file cut short.
- zstd compression of each message (``compression_mode: message``): :func:`unpacked` finds
  the payloads that are zstd frames (their magic number, where CDR starts with its
  encapsulation header) and decompresses them (a batch's frames in one call where every
  payload is a frame that decompresses), so a bag copied out of its directory without its
  metadata is read too.

Every scanner has :class:`.mcapread.McapScanner`'s interface: ``batches(workers)``,
``schemas``, ``channels``, ``truncated``, ``corrupt_messages``.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import tempfile
from collections.abc import Callable, Collection, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO, Protocol

import numpy as np

from pipe_nav_core.errors import BagFormatError
from pipe_nav_core.io.bagfiles import BagFile
from pipe_nav_core.io.cdr import gather
from pipe_nav_core.io.mcapread import (
    MESSAGE_HEADER_SIZE,
    ChannelRecord,
    McapScanner,
    MessageBatch,
    SchemaRecord,
)

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"  # the first bytes of a zstd frame (a CDR payload starts 00 0x)
DB3_BATCH_ROWS = 8192  # message ids per batch of a sqlite3 file
_DB3_COLUMNS = "id, topic_id, timestamp, data"  # a row as Db3Scanner reads it
_PAD = bytes(MESSAGE_HEADER_SIZE)  # where a Message record's header would be
_COPY_BYTES = 1 << 22  # bytes per write of a file decompressed into a temporary one
_STREAM_BYTES = 1 << 20  # compressed bytes per step of a file's decompression


class Scanner(Protocol):
    """What the reader and bag_info take from a file: its batches and what they met."""

    schemas: dict[int, SchemaRecord]
    channels: dict[int, ChannelRecord]
    truncated: bool
    corrupt_messages: dict[int, int]

    def batches(self, workers: int = 0) -> Iterator[MessageBatch]: ...


def payload_batch(
    payloads: Sequence[bytes | memoryview], channel: np.ndarray, log_time: np.ndarray
) -> MessageBatch:
    """A MessageBatch of the given payloads (each preceded by room for a record header, so
    that payload i is read where MessageBatch says)."""
    sizes = np.fromiter(map(len, payloads), dtype=np.int64, count=len(payloads))
    rec = np.zeros(len(payloads), dtype=np.int64)
    if len(sizes) > 1:
        np.cumsum(sizes[:-1] + MESSAGE_HEADER_SIZE, out=rec[1:])
    parts: list[bytes | memoryview] = [_PAD] * (2 * len(payloads))
    parts[1::2] = payloads
    buf = np.frombuffer(b"".join(parts), dtype=np.uint8)
    return MessageBatch(buf, rec, np.asarray(channel, dtype=np.int64),
                        np.asarray(log_time, dtype=np.int64), sizes)  # fmt: skip


def unpacked(batch: MessageBatch) -> MessageBatch:
    """The batch with its zstd-compressed payloads (rosbag2's compression of each message)
    decompressed; the batch itself when it has none. A frame that does not decompress is
    kept as it is (its decoding then fails and counts it)."""
    if not len(batch):
        return batch
    start = batch.payload_start
    if ZSTD_MAGIC[0] not in batch.buf.take(start, mode="clip"):  # 0.02 s over a 10 km bag
        return batch
    import zstandard

    d, error = zstandard.ZstdDecompressor(), zstandard.ZstdError
    payloads = _frames_at_once(batch, d, zstandard)
    if payloads is not None:
        return payload_batch(payloads, batch.channel, batch.log_time)
    mv = memoryview(batch.buf)
    spans = zip(start.tolist(), batch.size.tolist(), strict=True)
    payloads = [_frame(d, error, mv[s : s + n]) for s, n in spans]
    return payload_batch(payloads, batch.channel, batch.log_time)


def _frames_at_once(batch: MessageBatch, d: Any, zstandard: Any) -> list[Any] | None:
    """Every payload of the batch decompressed in one call (zstandard's loop in C, 0.7 s less
    than frame by frame over a 10 km bag's 1.6 M frames) where all of them are zstd frames and
    decompress; else None (then :func:`_frame` takes them one by one, and keeps what does not
    decompress). ``d``: a zstandard.ZstdDecompressor; the payloads as buffer objects."""
    start, size = batch.payload_start, batch.size
    if not (size >= len(ZSTD_MAGIC)).all():
        return None
    magic = np.frombuffer(ZSTD_MAGIC, dtype=np.uint8)
    if not (gather(batch.buf, start, len(ZSTD_MAGIC)) == magic).all():
        return None
    segments = np.column_stack([start, size]).astype(np.uint64)
    try:
        frames = zstandard.BufferWithSegments(batch.buf, segments.tobytes())
        out = d.multi_decompress_to_buffer(frames)
    except (zstandard.ZstdError, AttributeError, NotImplementedError, ValueError):
        return None  # a frame without its size or damaged (or a backend without the call)
    return list(map(out.__getitem__, range(len(out))))


def _frame(d: Any, error: type[Exception], p: memoryview) -> bytes | memoryview:
    """A payload decompressed if it is a zstd frame (``d``: a zstandard.ZstdDecompressor,
    ``error`` its exception), else (or if it does not decompress) as it is."""
    if len(p) < 4 or p[:4] != ZSTD_MAGIC:
        return p
    try:
        return d.decompress(p)
    except error:  # no content size in the frame header: streamed
        try:
            return d.decompressobj().decompress(p)
        except error:
            return p


class Db3Scanner:
    """Reader of one rosbag2 sqlite3 file with McapScanner's interface; ``topics``: the
    topic names whose messages are read (None: all). Channel and schema ids are the file's
    topic ids; the schemas carry the type names (no definitions: the reader knows its types
    by name).

    The messages are read a range of DB3_BATCH_ROWS ids at a time, each range's payloads,
    lengths, topics and stamps concatenated by SQLite itself (``group_concat``) in one step
    that lets go of the GIL, without a Python object per message. A range that does not
    read so (a damaged page, a payload that is not a blob) is read row by row, the rows
    after a damaged page too; so is a table whose ids are not its rowids (not rosbag2's)."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        warn: Callable[[str], None],
        topics: Collection[str] | None = None,
    ) -> None:
        self.path = os.fspath(path)
        self.warn = warn
        self.truncated = False
        self.corrupt_messages: dict[int, int] = {}
        self.schemas: dict[int, SchemaRecord] = {}
        self.channels: dict[int, ChannelRecord] = {}
        try:
            # used by one thread at a time: this one, or the batches' read-ahead thread
            self._db = sqlite3.connect(f"file:{Path(self.path).resolve()}?mode=ro", uri=True,
                                       check_same_thread=False)  # fmt: skip
            rows = self._db.execute(
                "SELECT id, name, type, serialization_format FROM topics"
            ).fetchall()
            (text_encoding,) = self._db.execute("PRAGMA encoding").fetchone()
            keys = [(c[1], c[2].upper()) for c in self._db.execute("PRAGMA table_info(messages)")
                    if c[5]]  # fmt: skip
        except sqlite3.Error as exc:
            raise BagFormatError(f"not a readable rosbag2 sqlite3 file ({exc})") from None
        for tid, name, typename, encoding in rows:
            self.schemas[tid] = SchemaRecord(tid, str(typename), "ros2msg", b"")
            self.channels[tid] = ChannelRecord(tid, tid, str(name), str(encoding), {})
        self._wanted = [c.id for c in self.channels.values()
                        if topics is None or c.topic in topics]  # fmt: skip
        self._all = len(self._wanted) == len(self.channels)  # no topic to leave out
        self._db.text_factory = bytes  # group_concat's text is the payloads' bytes
        # the aggregates where the bytes are not translated and the rows are walked in id
        # order: ids that are the rowids (rosbag2's id INTEGER PRIMARY KEY); else rows
        self._concat = text_encoding == "UTF-8" and keys == [("id", "INTEGER")]

    def batches(self, workers: int = 0) -> Iterator[MessageBatch]:
        """The messages of the wanted topics in recording order (the table's ids), in
        batches of at most DB3_BATCH_ROWS; ``workers`` is not used: a thread of its own asks
        SQLite for the next range while this one decodes the last (SQLite's step, most of
        the reading, lets go of the GIL)."""
        del workers
        try:
            if not self._wanted:
                return
            try:
                lo, hi = self._db.execute("SELECT min(id), max(id) FROM messages").fetchone()
            except sqlite3.Error as exc:
                self.truncated = True
                self.warn(f"{self.path}: no message could be read ({exc})")
                return
            if lo is None:
                return
            if not self._concat:
                yield from self._rows(lo, hi)
                return
            firsts = range(lo, hi + 1, DB3_BATCH_ROWS)
            with ThreadPoolExecutor(1, thread_name_prefix="db3-read") as ahead:
                fetch = ahead.submit(self._concatenated, firsts[0])
                for k, first in enumerate(firsts):
                    values = fetch.result()  # no query in flight from here
                    nxt = firsts[k + 1] if k + 1 < len(firsts) else None
                    batch = None if values is None else _concatenated_batch(values)
                    if batch is None:  # read row by row before the next range is asked for
                        yield from self._rows(first, first + DB3_BATCH_ROWS - 1)
                    if nxt is not None:
                        fetch = ahead.submit(self._concatenated, nxt)
                    if batch is not None and len(batch):
                        yield batch
        finally:
            self._db.close()

    def _query(self, columns: str, first: int, last: int, order: str = "ORDER BY id") -> Any:
        """``columns`` of the wanted messages with ids first..last (a sqlite3 cursor). For
        the aggregates (``order`` ""), the table is walked by its rowids only (NOT INDEXED:
        never by the stamps' index), so that they see the rows in id order."""
        where = "" if self._all else f"AND topic_id IN ({','.join(map(str, self._wanted))})"
        table = "messages" if order else "messages NOT INDEXED"
        return self._db.execute(
            f"SELECT {columns} FROM {table} WHERE id BETWEEN ? AND ? {where} {order}",
            (first, last),
        )

    def _concatenated(self, first: int) -> tuple[Any, ...] | None:
        """The payloads, lengths, topic ids and stamps of the wanted messages with ids
        first..first + DB3_BATCH_ROWS - 1, each concatenated by SQLite (an aggregate over a
        rowid range, in id order); None where they do not read so. Run by the read-ahead
        thread of :meth:`batches` while no other query runs."""
        columns = "group_concat(data, x''), group_concat(length(data)), " \
                  "group_concat(topic_id), group_concat(timestamp)"  # fmt: skip
        try:
            return tuple(self._query(columns, first, first + DB3_BATCH_ROWS - 1, "").fetchone())
        except sqlite3.Error:
            return None

    def _rows(self, first: int, last: int) -> Iterator[MessageBatch]:
        """The messages with ids first..last read row by row (in batches of at most
        DB3_BATCH_ROWS); where a row does not read, the reading goes on from the next id
        that does, and a warning names the ids lost."""
        rows: list[Any] = []
        lost: list[str] = []
        why = ""
        at = first  # the first id not read yet
        while at <= last:
            try:
                cur = self._query(_DB3_COLUMNS, at, last)
                while row := cur.fetchone():  # one by one: a row that fails loses no other
                    rows.append(row)
                    at = row[0] + 1
                    if len(rows) == DB3_BATCH_ROWS:
                        yield _rows_batch(rows)
                        rows = []
                break
            except sqlite3.Error as exc:
                why = str(exc)
            nxt = self._next_readable(at, last)
            lost.append(f"{at} to {nxt - 1}")
            at = nxt
        if lost:
            self.truncated = True
            self.warn(f"{self.path}: the messages with ids {', '.join(lost)} are unreadable "
                      f"({why}); the rest was read")  # fmt: skip
        if rows:
            yield _rows_batch(rows)

    def _next_readable(self, bad: int, last: int) -> int:
        """The smallest id after ``bad`` (an id whose row does not read) from which the rows
        read again (last + 1 if none): steps of 1, 2, 4 ... then halving back."""
        step = 1
        while bad + step <= last and not self._readable(bad + step, last):
            step *= 2
        lo, hi = bad + step // 2, min(bad + step, last + 1)  # lo does not read, hi does
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if self._readable(mid, last) else (mid, hi)
        return hi

    def _readable(self, first: int, last: int) -> bool:
        """Whether the first wanted message with an id in first..last reads (or none is)."""
        try:
            self._query(_DB3_COLUMNS, first, last).fetchone()
        except sqlite3.Error:
            return False
        return True


def _rows_batch(rows: Sequence[Any]) -> MessageBatch:
    """The batch of rows (id, topic id, stamp, payload) as :meth:`Db3Scanner._rows` reads
    them (a payload that is not bytes is empty: its decoding fails and counts it)."""
    _, tid, stamp, data = zip(*rows, strict=True)
    payloads = [d if isinstance(d, bytes) else b"" for d in data]
    return payload_batch(payloads, np.array(tid), np.array(stamp))


def _concatenated_batch(values: tuple[Any, ...]) -> MessageBatch | None:
    """The batch of what :meth:`Db3Scanner._concatenated` read (the payloads one after
    another, then the lengths, topic ids and stamps as comma-separated integers); None when
    they do not agree (a payload that is not a blob: text is counted in characters)."""
    data, *columns = values
    if data is None:  # no message in the range
        return payload_batch([], np.zeros(0), np.zeros(0))
    if not all(isinstance(v, bytes) for v in values):
        return None
    size, tid, stamp = (np.fromstring(v, dtype=np.int64, sep=",") for v in columns)
    if not (len(size) == len(tid) == len(stamp) and size.sum() == len(data)):
        return None
    rec = np.zeros(len(size), dtype=np.int64)
    np.cumsum(size[:-1], out=rec[1:])
    buf = np.frombuffer(_PAD + data, dtype=np.uint8)  # payload i at rec[i] + the header
    return MessageBatch(buf, rec, tid, stamp, size)


@contextmanager
def open_scanner(
    f: BagFile, warn: Callable[[str], None], topics: Collection[str] | None = None
) -> Iterator[Scanner]:
    """A scanner of one bag file whatever its form (raises BagFormatError or OSError when
    it cannot be read at all); ``topics``: the topics a sqlite3 file is asked for. A
    zstd-compressed MCAP file is scanned as it decompresses; a compressed sqlite3 file is
    decompressed into a temporary file first (SQLite reads files only)."""
    if not f.compressed:
        yield _scanner(f.path, f.storage, warn, topics)
        return
    with open(f.path, "rb") as src:
        if src.read(4) != ZSTD_MAGIC:
            raise BagFormatError("not a zstd-compressed file (bad magic)")
        src.seek(0)
        stream = ZstdStream(src, f.path, warn)
        if f.storage == "sqlite3":
            with _decompressed(f.path, stream) as plain:
                yield _scanner(plain, f.storage, warn, topics)
        else:
            yield McapScanner(f.path, warn, stream=stream.read)


def _scanner(
    path: Path, storage: str, warn: Callable[[str], None], topics: Collection[str] | None
) -> Scanner:
    if storage == "sqlite3":
        return Db3Scanner(path, warn, topics)
    return McapScanner(path, warn)


class ZstdStream:
    """The decompressed bytes of a zstd-compressed file (``src``, named ``path``), read
    forward by :meth:`read`, frame after frame. Where the compressed data end inside a frame
    or are damaged, what decompressed before is read and ``warn`` is told once."""

    def __init__(self, src: BinaryIO, path: Path, warn: Callable[[str], None]) -> None:
        import zstandard

        self._src, self._path, self._warn = src, path, warn
        self._d = zstandard.ZstdDecompressor()
        self._obj = self._d.decompressobj()
        self._error = zstandard.ZstdError
        self._out = bytearray()  # decompressed, not read yet
        self._ended = True  # the data so far end where a frame ends
        self._done = False  # nothing more decompresses

    def read(self, n: int) -> bytes:
        """The next ``n`` bytes (fewer only at the end of what decompresses)."""
        while len(self._out) < n and not self._done:
            self._more()
        with memoryview(self._out) as mv:
            part = bytes(mv[:n])
        del self._out[:n]
        return part

    def _more(self) -> None:
        """The next block of the file decompressed onto what is not read yet; at its end, or
        where it does not decompress, no more."""
        data = self._src.read(_STREAM_BYTES)
        if not data:
            self._finish("" if self._ended else "the last frame is cut off")
            return
        try:
            while data:
                self._out += self._obj.decompress(data)
                self._ended = self._obj.eof
                if not self._ended:  # all of data taken, the frame goes on
                    break
                data = self._obj.unused_data  # the next frame (rosbag2 writes one, others more)
                self._obj = self._d.decompressobj()
        except self._error as exc:
            self._finish(str(exc))

    def _finish(self, why: str) -> None:
        self._done = True
        if why:
            self._warn(f"{self._path}: the compressed data end early or are damaged ({why}); "
                       "what decompressed before that was read")  # fmt: skip


@contextmanager
def _decompressed(path: Path, stream: ZstdStream) -> Iterator[Path]:
    """A compressed file's ``stream`` written into a temporary file (removed after)."""
    inner = path.with_suffix("").suffix or ".mcap"
    with tempfile.TemporaryDirectory(prefix="pipe_nav_bag_") as tmp:
        plain = Path(tmp) / f"decompressed{inner}"
        try:
            with open(plain, "wb") as out:
                shutil.copyfileobj(stream, out, _COPY_BYTES)
        except OSError as exc:  # a full temporary folder: name it
            why = f"cannot decompress it into {tmp} ({exc.strerror})"
            raise OSError(exc.errno, why) from None
        yield plain
