"""Reading ROS 2 bags (MCAP) into SensorLogs: whole (:func:`read_bag`) or streamed in time chunks
(:func:`iter_bag`).

The reader walks the bag's files (:mod:`.bagfiles`) batch by batch in recording (file) order
(:class:`.mcapread.McapScanner`), checks each channel's type (``unknown_type`` otherwise, with a
warning), decodes the messages of the four sensor roles (:mod:`.bagdecode`: ``bad_cdr``,
``nan``) and hands them to one :class:`.topic_checks.TopicState` per topic (``time_jump``,
``non_monotonic``, ``duplicate``, ``late``); the skip reasons are the ``SKIP_*`` constants of
:mod:`.topics`, counted and explained in the :class:`BagReport`. Sample times are the header
stamps, never the log times.

Streaming (:func:`iter_bag`) holds back ``lag_seconds`` of data behind the newest stamp of the
slowest topic (within ``STALL_S`` of the newest of all) before it hands out a time chunk; a
message that arrives after its chunk went out is dropped (``late``, with a warning), so in the
normal case the chunks concatenate exactly to :func:`read_bag`.
Cheap metadata without reading the messages through is :mod:`.baginfo`.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from pipe_nav_core.errors import BagError, BagFormatError, InputError, McapFormatError
from pipe_nav_core.io.bagdecode import VALUE_KEYS, Pieces, decode_role
from pipe_nav_core.io.bagfiles import bag_layout
from pipe_nav_core.io.bagforms import Scanner, open_scanner, unpacked
from pipe_nav_core.io.mcapread import McapScanner, MessageBatch
from pipe_nav_core.io.stamps import ns_to_sec, sec_to_ns_scalar
from pipe_nav_core.io.topic_checks import REORDER_WINDOW_S, TIME_JUMP_S, TopicState
from pipe_nav_core.io.topics import (
    DEFAULT_TOPICS,
    ROLE_TYPES,
    SKIP_BAD_CDR,
    SKIP_CORRUPT_CHUNK,
    SKIP_DUPLICATE,
    SKIP_LATE,
    SKIP_NAN,
    SKIP_NON_MONOTONIC,
    SKIP_TIME_JUMP,
    SKIP_UNKNOWN_TYPE,
    BagReport,
    TopicNames,
    normalize_type,
)
from pipe_nav_core.memory import Spool
from pipe_nav_core.types import (
    ImuSamples,
    MagSamples,
    OdometerSamples,
    SensorLog,
    empty_imu,
    empty_mag,
    empty_odometer,
)

EMIT_LAG_S = 5.0  # s: streaming holds back this much data behind the newest stamp
# s: ... of the slowest topic, unless it is this far behind the newest (an IMU stamping on a
# clock of its own, 10 s off the odometer's, lost 0.5 % of its samples as late before)
STALL_S = 30.0
READ_WORKERS_ENV = "PIPE_NAV_READ_WORKERS"  # threads that unpack the chunks (0: none)

_MISSING_HINT = {
    "imu": "",
    "odometer": "",
    "mag": " (optional magnetometer)",
    "markers": " (give the markers with a CSV file)",
}


def read_workers(workers: int | None = None, *, beside: int = 0) -> int:
    """Threads that unpack the chunks (decompress, CRC check, locate the messages) ahead
    of the decoding and the checks: ``workers`` when given (0: none, all in the calling
    thread), else the environment variable ``PIPE_NAV_READ_WORKERS``, else one where a core is
    left for it: the cores outnumber the reading thread and the ``beside`` threads the caller
    keeps busy meanwhile (the first filter pass: on two cores a third thread only takes CPU
    from it, and the pass is what the run waits for). More do not pay: the checks hold the
    GIL, and they are what is left to the calling thread. InputError (a ValueError) for a
    negative or non-integer count."""
    if workers is None:
        env = os.environ.get(READ_WORKERS_ENV, "").strip()
        if not env:
            return 1 if (os.cpu_count() or 1) >= 2 + beside else 0
        try:
            workers = int(env)
        except ValueError:
            raise InputError(f"{READ_WORKERS_ENV}={env!r}: not a whole number of threads") from None
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise InputError(f"read workers must be a whole number >= 0, got {workers!r}")
    return workers


# decoded messages gathered (some 3-4 chunks of 1 MiB) before they go through the topics'
# checks together
CHECK_MESSAGES = 10_000


class _BagReader:
    def __init__(
        self,
        path: str | os.PathLike[str],
        topics: TopicNames,
        report: BagReport | None,
        workers: int | None = None,
    ):
        self.path = Path(path)
        self.workers = read_workers(workers)
        self.layout = bag_layout(path)
        self.files = [f.path for f in self.layout]
        self.topics = topics
        self.report = report if report is not None else BagReport()
        self.report.path = str(self.path)
        self.report.files = [str(f) for f in self.files]
        by_topic = topics.roles()
        self.states = {role: TopicState(t, role, self.report) for t, role in by_topic.items()}
        self.role_of = by_topic
        for t in by_topic:
            self.report.counts.setdefault(t, 0)
        self.messages_read = 0
        self.decoded: dict[str, list[Pieces]] = {}  # by role, not yet through the checks
        self.n_decoded = 0
        # Fail early on a single plain MCAP file that is not MCAP at all.
        if len(self.layout) == 1 and self.layout[0].plain_mcap:
            self._check_magic(self.files[0])

    def _check_magic(self, f: Path) -> None:
        try:
            McapScanner(f, self.report.warn)
        except McapFormatError as exc:
            raise BagError(f"{f}: {exc}") from None
        except OSError as exc:
            raise BagError(f"{f}: cannot read ({exc.strerror or exc})") from None

    def _batches(self) -> Iterator[tuple[MessageBatch, dict[int, str]]]:
        """(batch, channel id -> role) over every file, with type checks."""
        usable = 0
        for bf in self.layout:
            f = bf.path
            if not f.is_file():
                self.report.truncated = True
                self.report.warn(f"{f}: listed in metadata.yaml but missing; skipped")
                continue
            try:
                with open_scanner(bf, self.report.warn, self.role_of) as sc:
                    usable += 1
                    yield from self._file_batches(sc)
            except (BagFormatError, OSError) as exc:
                if len(self.files) == 1:
                    why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
                    raise BagError(f"{f}: {why}") from None
                self.report.truncated = True
                self.report.warn(f"{f}: unreadable ({exc}); skipped")
        if usable == 0:
            raise BagError(f"{self.path}: no readable bag file")

    def _file_batches(self, sc: Scanner) -> Iterator[tuple[MessageBatch, dict[int, str]]]:
        warned: set[int] = set()
        for batch in sc.batches(self.workers):
            roles = self._channel_roles(sc, warned)
            yield unpacked(batch), roles
        if sc.truncated:
            self.report.truncated = True
        for cid, n in sc.corrupt_messages.items():
            ch = sc.channels.get(cid)
            if ch is not None and ch.topic in self.role_of:
                self.report.add_skipped(ch.topic, SKIP_CORRUPT_CHUNK, n)

    def _channel_roles(self, sc: Scanner, warned: set[int]) -> dict[int, str]:
        roles: dict[int, str] = {}
        for cid, ch in sc.channels.items():
            schema = sc.schemas.get(ch.schema_id)
            typename = normalize_type(schema.name) if schema is not None else ""
            if ch.topic not in self.report.types:
                self.report.types[ch.topic] = typename
            role = self.role_of.get(ch.topic)
            if role is None:
                continue
            expected = ROLE_TYPES[role]
            if typename != expected or ch.message_encoding != "cdr":
                roles[cid] = "!" + role
                if cid not in warned:
                    warned.add(cid)
                    got = typename or "no schema"
                    if ch.message_encoding != "cdr":
                        got += f", encoding {ch.message_encoding}"
                    self.report.warn(
                        f"{ch.topic}: carries {got}, expected {expected} (cdr); "
                        "its messages were skipped"
                    )
                continue
            roles[cid] = role
        return roles

    def _decode_batch(self, batch: MessageBatch, roles: dict[int, str]) -> None:
        """The batch's messages of each role decoded, kept for :meth:`_ingest_decoded`."""
        if len(batch) == 0:
            return
        # the channels present: ids are small, so counted (np.unique sorts: 0.037 s against
        # 0.011 s over the 596 batches of the 10 km bag)
        for cid in np.flatnonzero(np.bincount(batch.channel)).tolist():
            role = roles.get(cid)
            if role is None:
                continue
            sel = np.flatnonzero(batch.channel == cid)
            if role.startswith("!"):
                self.report.add_skipped(self.topics_of(role[1:]), SKIP_UNKNOWN_TYPE, len(sel))
                continue
            st = self.states[role]
            st.seen += len(sel)
            self.messages_read += len(sel)
            self.decoded.setdefault(role, []).append(
                decode_role(role, batch, sel, st.topic, self.report)
            )
            self.n_decoded += len(sel)

    def _ingest_decoded(self) -> None:
        """The decoded samples through their topics' checks, a few batches at a time (the
        checks are the same whatever the batches; fewer calls cost less of the GIL, which
        the first pass on the other core needs too)."""
        for role, parts in self.decoded.items():
            self.states[role].ingest(Pieces.concat(parts, VALUE_KEYS[role]))
        self.decoded, self.n_decoded = {}, 0

    def topics_of(self, role: str) -> str:
        return {
            "imu": self.topics.imu,
            "odometer": self.topics.odometer,
            "mag": self.topics.mag,
            "markers": self.topics.markers,
        }[role]

    def _high_water(self) -> int | None:
        """The stamp (ns) up to which the sensor topics have been read: the slowest topic's
        newest, but for topics STALL_S behind the newest of all (stopped, or on a clock of
        their own so far off that their samples are named late)."""
        hw = [s.high_water() for s in self.states.values() if s.role != "markers"]
        hw = [h for h in hw if h is not None]
        if not hw:
            return None
        top = max(hw)
        return min(h for h in hw if h >= top - sec_to_ns_scalar(STALL_S))

    def _lowest_buffered(self) -> int | None:
        lows = [int(p.ns.min()) for s in self.states.values() for p in s.buffer if len(p)]
        lows += [
            int(s.pending.ns.min())
            for s in self.states.values()
            if s.pending is not None and len(s.pending)
        ]
        return min(lows) if lows else None

    def _emit(self, upto: int | None) -> SensorLog:
        parts = {s.role: s.emit(upto) for s in self.states.values()}
        imu, odo, mag, mk = parts["imu"], parts["odometer"], parts["mag"], parts["markers"]
        return SensorLog(
            imu=ImuSamples(ns_to_sec(imu.ns), imu.values["gyro"], imu.values["accel"])
            if len(imu)
            else empty_imu(),
            odometer=OdometerSamples(ns_to_sec(odo.ns), odo.values["distance"], odo.values["speed"])
            if len(odo)
            else empty_odometer(),
            mag=MagSamples(ns_to_sec(mag.ns), mag.values["field"]) if len(mag) else empty_mag(),
            markers=list(mk.values["marker"]),
        )

    def chunks(self, chunk_seconds: float, lag_seconds: float) -> Iterator[SensorLog]:
        streaming = math.isfinite(chunk_seconds)
        if streaming and chunk_seconds <= 0:
            raise ValueError("chunk_seconds must be positive")
        chunk_ns = sec_to_ns_scalar(chunk_seconds) if streaming else 0
        lag_ns = sec_to_ns_scalar(lag_seconds)
        next_b: int | None = None
        for batch, roles in self._batches():
            self._decode_batch(batch, roles)
            if self.n_decoded < CHECK_MESSAGES:
                continue
            self._ingest_decoded()
            if not streaming:
                continue
            hw = self._high_water()
            if hw is None:
                continue
            if next_b is None:
                low = self._lowest_buffered()
                if low is None:
                    continue
                next_b = (low // chunk_ns + 1) * chunk_ns
            while next_b is not None and hw >= next_b + lag_ns:
                log = self._emit(next_b)
                if _log_len(log):
                    yield log
                low = self._lowest_buffered()
                # next chunk: the one holding the oldest buffered sample (skips empty stretches)
                next_b = (
                    None
                    if low is None
                    else max(next_b + chunk_ns, (low // chunk_ns + 1) * chunk_ns)
                )
        self._ingest_decoded()
        for s in self.states.values():
            s.flush_pending()
        if streaming:
            # hand out what is left, still one time chunk at a time
            while (low := self._lowest_buffered()) is not None:
                log = self._emit((low // chunk_ns + 1) * chunk_ns)
                if _log_len(log):
                    yield log
        else:
            yield self._emit(None)
        self._finish()

    def _finish(self) -> None:
        r = self.report
        if self.messages_read == 0 and r.truncated and not any(r.counts.values()):
            raise BagError(f"{self.path}: truncated or corrupt before any message could be read")
        for s in self.states.values():
            if s.seen == 0 and not r.skipped_by_topic.get(s.topic):
                r.warn(f"{s.topic}: no messages in the bag{_MISSING_HINT[s.role]}")
        for topic, reasons in r.skipped_by_topic.items():
            for reason, n in reasons.items():
                r.warn(f"{topic}: dropped {n} message(s): {_REASON_TEXT.get(reason, reason)}")


_REASON_TEXT = {
    SKIP_NAN: "NaN or infinite values",
    SKIP_BAD_CDR: "payload could not be deserialized",
    SKIP_NON_MONOTONIC: f"stamp more than {REORDER_WINDOW_S} s older than the newest one",
    SKIP_DUPLICATE: "repeated stamp",
    SKIP_TIME_JUMP: f"isolated stamp more than {TIME_JUMP_S} s ahead of its neighbours",
    SKIP_LATE: "arrived after its time chunk was handed out (streaming)",
    SKIP_UNKNOWN_TYPE: "unexpected message type",
    SKIP_CORRUPT_CHUNK: "in a corrupt chunk",
}


def _log_len(log: SensorLog) -> int:
    return len(log.imu) + len(log.odometer) + len(log.mag) + len(log.markers)


# ----------------------------------------------------------------------------- public API


PIECE_S = 60.0  # s of stamps in each time chunk read_bag hands to ``pieces``


def read_bag(
    path: str | os.PathLike[str],
    topics: TopicNames = DEFAULT_TOPICS,
    *,
    workers: int | None = None,
    pieces: Callable[[SensorLog, BagReport], None] | None = None,
    spill_imu_bytes: int | None = None,
) -> tuple[SensorLog, BagReport]:
    """Read a whole bag (single .mcap or rosbag2 directory) into a SensorLog.

    Every topic comes out strictly increasing in header stamp (seconds), vectors in their
    message frame (imu_link), markers sorted by time. Problems are counted and described in
    the returned BagReport; a file that cannot be read at all raises BagError.

    ``workers``: threads that decompress and check the chunks a few ahead of the
    decoding (:func:`read_workers`; default one on two cores or more); everything else runs in
    this thread in file order, so the log and the report are exactly those of ``workers=0``.
    ``pieces``: told each time chunk of PIECE_S s (:func:`iter_bag`'s) and the report so far
    as the bag is read, so that work on the start of the run can begin before its end is
    read; the log is then those chunks concatenated (the same, tested).
    ``spill_imu_bytes``: once more IMU samples than this (bytes) are read, they are gathered
    in temporary files as the bag is read and the log's IMU arrays are mapped from them,
    read-only (memory.Spool; the same values): a long run's IMU (0.58 GB at 100 km) is then
    not in memory twice, as the chunks and as the log joined from them.
    """
    reader = _BagReader(path, topics, None, workers)
    if pieces is None and spill_imu_bytes is None:
        logs = list(reader.chunks(math.inf, 0.0))
        return (logs[0] if logs else SensorLog()), reader.report
    gathered = _Gathered(spill_imu_bytes)
    for log in reader.chunks(PIECE_S, EMIT_LAG_S):
        if pieces is not None:
            pieces(log, reader.report)
        gathered.add(log)
    return gathered.log(), reader.report


class _Gathered:
    """The time chunks of a bag, joined into its log at the end; the IMU samples, once more
    than ``spill`` bytes of them are read, in temporary files (memory.Spool) instead of in
    the chunks."""

    def __init__(self, spill: int | None) -> None:
        self.spill = spill
        self.logs: list[SensorLog] = []
        self.imu_bytes = 0
        self.spools: tuple[Spool, Spool, Spool] | None = None

    def add(self, log: SensorLog) -> None:
        imu = log.imu
        self.imu_bytes += imu.t.nbytes + imu.gyro.nbytes + imu.accel.nbytes
        if self.spools is None and self.spill is not None and self.imu_bytes > self.spill:
            self.spools = (Spool(), Spool((3,)), Spool((3,)))
            self.logs = [self._spooled(x) for x in self.logs]
        self.logs.append(log if self.spools is None else self._spooled(log))

    def _spooled(self, log: SensorLog) -> SensorLog:
        assert self.spools is not None
        for spool, a in zip(self.spools, (log.imu.t, log.imu.gyro, log.imu.accel), strict=True):
            spool.append(a)
        return dataclasses.replace(log, imu=empty_imu())

    def log(self) -> SensorLog:
        log = concat_logs(self.logs)
        if self.spools is None:
            return log
        t, gyro, accel = (s.gathered() for s in self.spools)
        return dataclasses.replace(log, imu=ImuSamples(t, gyro, accel))


def iter_bag(
    path: str | os.PathLike[str],
    topics: TopicNames = DEFAULT_TOPICS,
    chunk_seconds: float = 60.0,
    report: BagReport | None = None,
    *,
    lag_seconds: float = EMIT_LAG_S,
    workers: int | None = None,
) -> Iterator[SensorLog]:
    """Stream a bag as consecutive time chunks of about ``chunk_seconds`` of header-stamp time.

    Memory stays bounded: the MCAP chunks being unpacked (at most two per worker thread, see
    :func:`read_bag` for ``workers``, plus one) plus ``lag_seconds`` + one chunk of decoded
    samples. Chunk k holds the samples with stamps in [b_k, b_k+1) (b_k are multiples of
    chunk_seconds; empty chunks are not yielded); each topic is strictly increasing within and
    across chunks; markers are in the chunk containing their stamp. Pass a BagReport as
    ``report`` to read the counts and warnings after the iteration (the generator's return value
    is the same report). BagError for an unreadable bag is raised by this call.
    """
    reader = _BagReader(path, topics, report, workers)

    def gen() -> Iterator[SensorLog]:
        yield from reader.chunks(float(chunk_seconds), float(lag_seconds))
        return reader.report

    return gen()


def concat_logs(logs: Sequence[SensorLog]) -> SensorLog:
    """Concatenate time chunks (e.g. from iter_bag) into one SensorLog."""
    logs = list(logs)
    if not logs:
        return SensorLog()
    return SensorLog(
        imu=ImuSamples(
            np.concatenate([x.imu.t for x in logs]),
            np.concatenate([x.imu.gyro for x in logs]),
            np.concatenate([x.imu.accel for x in logs]),
        ),
        odometer=OdometerSamples(
            np.concatenate([x.odometer.t for x in logs]),
            np.concatenate([x.odometer.distance for x in logs]),
            np.concatenate([x.odometer.speed for x in logs]),
        ),
        mag=MagSamples(
            np.concatenate([x.mag.t for x in logs]), np.concatenate([x.mag.field for x in logs])
        ),
        markers=sorted((m for x in logs for m in x.markers), key=lambda m: m.t),
    )
