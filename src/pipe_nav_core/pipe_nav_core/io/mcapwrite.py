"""Low-level MCAP writing: a fast, chunked, indexed writer for pre-serialized message streams.

Each topic is a *stream*: time-sorted log times (ns) and a callback that serializes a range of
its messages into ready MCAP Message records (see :func:`message_records`). The writer merges
the streams in log-time order, cuts ~``chunk_size`` chunks, compresses them and writes a full
MCAP file the way rosbag2's MCAP storage does: profile ``ros2``, Schema and Channel records
first, chunks each followed by their MessageIndex records, Metadata records (rosbag2 keeps its
bag metadata in one named ``rosbag2``), DataEnd, then a summary (schemas, channels, statistics,
chunk indexes, metadata indexes, summary offsets) and the footer, with CRCs. Nothing is done
per message in Python except assembling the chunk (a list join).

The few records written once per file or per chunk (Header, Schema, Channel, Metadata,
Attachment, their indexes, Statistics, ChunkIndex, SummaryOffset, DataEnd, Footer) are built by
the ``mcap`` library's record classes (:mod:`mcap.records`); the Message, Chunk and
MessageIndex records, which carry every message, are assembled here with numpy.

About 430 lines, one module on purpose: the MCAP record layouts and the chunked writer that
emits them are one format, read together with the specification.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np
from isal.isal_zlib import crc32  # zlib's CRC-32, about three times faster
from mcap.data_stream import RecordBuilder
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from numpy.typing import NDArray

from pipe_nav_core.io.mcaprecords import (
    MAGIC,
    MESSAGE_HEADER_SIZE,
    OP_ATTACHMENT_INDEX,
    OP_CHANNEL,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_METADATA_INDEX,
    OP_SCHEMA,
    OP_STATISTICS,
)

DEFAULT_CHUNK_SIZE = 4 << 20  # bytes of uncompressed records per chunk


def _s(text: str) -> bytes:
    raw = text.encode("utf-8")
    return struct.pack("<I", len(raw)) + raw


def _record(op: int, content: bytes) -> bytes:
    return struct.pack("<BQ", op, len(content)) + content


def _bytes(record: McapRecord) -> bytes:
    """The bytes of one record (opcode, length, content) as the mcap library writes it."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def message_records(
    payloads: NDArray[np.uint8], channel_id: int, log_times: NDArray[np.int64], seq0: int = 0
) -> NDArray[np.uint8]:
    """Fill the MCAP Message record header into rows ``payloads[:, :31]`` in place.

    payloads: (n, 31 + payload_size) uint8 whose columns 31: hold the CDR payloads; log_times:
    (n,) ns used as both log_time and publish_time. Returns payloads.
    """
    n, width = payloads.shape
    payloads[:, 0] = OP_MESSAGE
    payloads[:, 1:9] = np.array([width - 9], dtype="<u8").view(np.uint8)
    payloads[:, 9:11] = np.array([channel_id], dtype="<u2").view(np.uint8)
    payloads[:, 11:15] = (
        (np.arange(n, dtype=np.int64) + seq0).astype("<u4").view(np.uint8).reshape(n, 4)
    )
    lt = np.ascontiguousarray(log_times, dtype="<u8").view(np.uint8).reshape(n, 8)
    payloads[:, 15:23] = lt
    payloads[:, 23:31] = lt
    return payloads


def variable_records(channel_id: int, log_times: Sequence[int], payloads: Sequence[bytes]) -> bytes:
    """Message records for a few variable-size payloads (concatenated)."""
    out = []
    for i, (t, p) in enumerate(zip(log_times, payloads, strict=True)):
        out.append(
            struct.pack("<BQHIQQ", OP_MESSAGE, 22 + len(p), channel_id, i, int(t), int(t)) + p
        )
    return b"".join(out)


@dataclass
class Stream:
    """Messages of one channel: log_times (n,) int64 ns non-decreasing; sizes (n,) int64 record
    sizes (31 + payload); encode(a, b) -> bytes-like of the records of messages a..b-1."""

    channel_id: int
    log_times: NDArray[np.int64]
    sizes: NDArray[np.int64]
    encode: Callable[[int, int], object]

    @staticmethod
    def fixed(
        channel_id: int,
        log_times: NDArray[np.int64],
        record_size: int,
        encode: Callable[[int, int], object],
    ) -> Stream:
        lt = np.asarray(log_times, dtype=np.int64)
        return Stream(channel_id, lt, np.full(len(lt), record_size, dtype=np.int64), encode)

    @staticmethod
    def variable(channel_id: int, log_times: Sequence[int], payloads: Sequence[bytes]) -> Stream:
        lt = np.asarray(log_times, dtype=np.int64)
        recs = variable_records(channel_id, [int(x) for x in lt], payloads)
        sizes = np.array([MESSAGE_HEADER_SIZE + len(p) for p in payloads], dtype=np.int64)
        starts = np.concatenate([[0], np.cumsum(sizes)])

        def enc(a: int, b: int) -> object:
            return memoryview(recs)[int(starts[a]) : int(starts[b])]

        return Stream(channel_id, lt, sizes, enc)


def _compressor(compression: str) -> Callable[[bytes], bytes]:
    if compression == "":
        return lambda data: data
    if compression == "zstd":
        try:
            import zstandard

            return zstandard.ZstdCompressor(level=1).compress
        except ImportError:  # pragma: no cover - depends on the environment
            from backports import zstd  # type: ignore[import-not-found]

            return lambda data: zstd.compress(data, level=1)
    if compression == "lz4":
        import lz4.frame

        return lambda data: lz4.frame.compress(data)
    raise ValueError(f"unsupported compression {compression!r}")


class McapWriter:
    """Writes one MCAP file to an open binary file object (see the module docstring).

    Call :meth:`add_schema`, :meth:`add_channel`, then :meth:`write_streams` (once), then
    :meth:`add_metadata` and :meth:`add_attachment` (any number), then :meth:`finish`.
    ``message_count``, ``channel_counts`` (channel id -> messages), ``start_time`` and
    ``end_time`` (log times, ns) describe what was written so far.
    """

    def __init__(
        self,
        f: BinaryIO,
        *,
        profile: str = "ros2",
        library: str = "pipe_nav_core",
        compression: str = "zstd",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
    ) -> None:
        self.f = f
        self.compression = compression
        self.compress = _compressor(compression)
        self.chunk_size = int(chunk_size)
        self.pos = 0
        self.crc = 0
        self.schemas: list[bytes] = []
        self.channels: list[bytes] = []
        self.chunk_indexes: list[bytes] = []
        self.metadata_indexes: list[bytes] = []
        self.attachment_indexes: list[bytes] = []
        self.channel_counts: dict[int, int] = {}
        self.start_time: int | None = None
        self.end_time: int | None = None
        self.message_count = 0
        self._write(MAGIC)
        self._write(_bytes(Header(profile=profile, library=library)))

    def _write(self, data: bytes | memoryview) -> None:
        self.f.write(data)
        self.crc = crc32(data, self.crc)
        self.pos += len(data)

    def add_schema(self, sid: int, name: str, encoding: str, data: str) -> int:
        rec = _bytes(Schema(id=sid, name=name, encoding=encoding, data=data.encode("utf-8")))
        self.schemas.append(rec)
        self._write(rec)
        return sid

    def add_channel(
        self, cid: int, schema_id: int, topic: str, message_encoding: str, metadata: dict[str, str]
    ) -> int:
        rec = _bytes(
            Channel(
                id=cid,
                schema_id=schema_id,
                topic=topic,
                message_encoding=message_encoding,
                metadata=metadata,
            )
        )
        self.channels.append(rec)
        self.channel_counts.setdefault(cid, 0)
        self._write(rec)
        return cid

    def add_metadata(self, name: str, metadata: dict[str, str]) -> None:
        """Write a Metadata record (a named string map) into the data section and index it in
        the summary (rosbag2 reads its bag metadata from the one named ``rosbag2``)."""
        rec = _bytes(Metadata(name=name, metadata=metadata))
        offset = self.pos
        self._write(rec)
        self.metadata_indexes.append(
            _bytes(MetadataIndex(offset=offset, length=len(rec), name=name))
        )

    def add_attachment(
        self, name: str, media_type: str, data: bytes, log_time: int = 0, create_time: int = 0
    ) -> None:
        """Write an Attachment record (a named file, e.g. ``welds.csv`` of media type
        ``text/csv``; times ns) into the data section, with its CRC, and index it in the
        summary."""
        rec = _bytes(
            Attachment(
                create_time=create_time,
                log_time=log_time,
                name=name,
                media_type=media_type,
                data=data,
            )
        )
        offset = self.pos
        self._write(rec)
        self.attachment_indexes.append(
            _bytes(
                AttachmentIndex(
                    offset=offset,
                    length=len(rec),
                    log_time=log_time,
                    create_time=create_time,
                    data_size=len(data),
                    name=name,
                    media_type=media_type,
                )
            )
        )

    def write_streams(self, streams: Sequence[Stream]) -> None:
        """Merge the streams in log-time order (ties: stream order) and write them in chunks."""
        streams = [s for s in streams if len(s.log_times)]
        if not streams:
            return
        t_all = np.concatenate([s.log_times for s in streams])
        k_all = np.concatenate([np.full(len(s.log_times), k) for k, s in enumerate(streams)])
        i_all = np.concatenate([np.arange(len(s.log_times)) for s in streams])
        size_all = np.concatenate([s.sizes for s in streams])
        order = np.lexsort((k_all, t_all))
        t_m, k_m, i_m, size_m = t_all[order], k_all[order], i_all[order], size_all[order]
        del t_all, k_all, i_all, size_all, order
        cum = np.cumsum(size_m) - size_m
        chunk_of = cum // self.chunk_size
        bounds = np.flatnonzero(np.diff(chunk_of)) + 1
        edges = np.concatenate([[0], bounds, [len(t_m)]])
        for a, b in zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True):
            self._write_chunk(streams, t_m[a:b], k_m[a:b], i_m[a:b], size_m[a:b])

    def _write_chunk(
        self,
        streams: Sequence[Stream],
        t: NDArray[np.int64],
        k: NDArray[np.int64],
        i: NDArray[np.int64],
        size: NDArray[np.int64],
    ) -> None:
        # Serialize each stream's (contiguous) share of this chunk.
        regions: list[memoryview] = []
        region_of = np.zeros(len(streams), dtype=np.int64)
        first_of = np.zeros(len(streams), dtype=np.int64)
        base = np.zeros(len(streams) + 1, dtype=np.int64)
        present = np.unique(k)
        for j, kk in enumerate(present.tolist()):
            sel = i[k == kk]
            a, b = int(sel[0]), int(sel[-1]) + 1
            raw = streams[kk].encode(a, b)
            mv = memoryview(raw).cast("B") if not isinstance(raw, memoryview) else raw.cast("B")
            regions.append(mv)
            region_of[kk] = j
            first_of[kk] = a
            base[j + 1] = base[j] + len(mv)
        # Offset of every message within its stream region.
        src_start = np.empty(len(t), dtype=np.int64)
        for kk in present.tolist():
            m = k == kk
            sz = size[m]
            src_start[m] = base[region_of[kk]] + np.cumsum(sz) - sz
        whole = memoryview(b"".join(regions)) if len(regions) > 1 else regions[0]
        # Consecutive messages of one stream are contiguous in its region: copy runs.
        first = np.concatenate([[0], np.flatnonzero(np.diff(k)) + 1])
        last = np.concatenate([first[1:] - 1, [len(k) - 1]])
        run_a = src_start[first].tolist()
        run_b = (src_start[last] + size[last]).tolist()
        records = b"".join([whole[s:e] for s, e in zip(run_a, run_b, strict=True)])
        dst = np.cumsum(size) - size

        usize = len(records)
        crc = crc32(records)
        data = self.compress(records)
        start_t, end_t = int(t.min()), int(t.max())
        content = (
            struct.pack("<QQQI", start_t, end_t, usize, crc)
            + _s(self.compression)
            + struct.pack("<Q", len(data))
        )
        chunk_start = self.pos
        self._write(struct.pack("<BQ", OP_CHUNK, len(content) + len(data)))
        self._write(content)
        self._write(data)
        chunk_len = self.pos - chunk_start

        index_offsets: dict[int, int] = {}
        mi_start = self.pos
        cids = np.array([streams[kk].channel_id for kk in range(len(streams))], dtype=np.int64)
        chan = cids[k]
        for cid in np.unique(chan).tolist():
            m = chan == cid
            pairs = np.empty((int(m.sum()), 2), dtype="<u8")
            pairs[:, 0] = t[m]
            pairs[:, 1] = dst[m]
            body = struct.pack("<HI", cid, pairs.nbytes) + pairs.tobytes()
            index_offsets[cid] = self.pos
            self._write(_record(OP_MESSAGE_INDEX, body))
            self.channel_counts[cid] = self.channel_counts.get(cid, 0) + int(m.sum())
        mi_len = self.pos - mi_start

        self.chunk_indexes.append(
            _bytes(
                ChunkIndex(
                    message_start_time=start_t,
                    message_end_time=end_t,
                    chunk_start_offset=chunk_start,
                    chunk_length=chunk_len,
                    message_index_offsets=index_offsets,
                    message_index_length=mi_len,
                    compression=self.compression,
                    compressed_size=len(data),
                    uncompressed_size=usize,
                )
            )
        )
        self.message_count += len(t)
        self.start_time = start_t if self.start_time is None else min(self.start_time, start_t)
        self.end_time = end_t if self.end_time is None else max(self.end_time, end_t)

    def finish(self) -> None:
        """Write DataEnd, the summary section, the footer and the closing magic."""
        self._write(_bytes(DataEnd(data_section_crc=self.crc)))
        summary_start = self.pos
        scrc = 0
        groups: list[tuple[int, int, int]] = []

        def put(op: int, recs: list[bytes]) -> None:
            nonlocal scrc
            if not recs:
                return
            start = self.pos
            for r in recs:
                self._write(r)
                scrc = crc32(r, scrc)
            groups.append((op, start, self.pos - start))

        put(OP_SCHEMA, self.schemas)
        put(OP_CHANNEL, self.channels)
        stats = _bytes(
            Statistics(
                message_count=self.message_count,
                schema_count=len(self.schemas),
                channel_count=len(self.channels),
                attachment_count=len(self.attachment_indexes),
                metadata_count=len(self.metadata_indexes),
                chunk_count=len(self.chunk_indexes),
                message_start_time=self.start_time or 0,
                message_end_time=self.end_time or 0,
                channel_message_counts=dict(sorted(self.channel_counts.items())),
            )
        )
        put(OP_STATISTICS, [stats])
        put(OP_CHUNK_INDEX, self.chunk_indexes)
        put(OP_ATTACHMENT_INDEX, self.attachment_indexes)
        put(OP_METADATA_INDEX, self.metadata_indexes)
        summary_offset_start = self.pos
        offs = [
            _bytes(SummaryOffset(group_opcode=op, group_start=s, group_length=n))
            for op, s, n in groups
        ]
        for r in offs:
            self._write(r)
            scrc = crc32(r, scrc)
        # the summary CRC covers the footer up to the CRC field itself
        footer_head = _bytes(
            Footer(
                summary_start=summary_start,
                summary_offset_start=summary_offset_start,
                summary_crc=0,
            )
        )[:-4]
        scrc = crc32(footer_head, scrc)
        self._write(footer_head + struct.pack("<I", scrc))
        self._write(MAGIC)
