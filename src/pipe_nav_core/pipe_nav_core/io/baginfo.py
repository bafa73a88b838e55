"""Cheap facts about a bag without reading it through: per-topic types, counts and first/last
stamps (:func:`bag_info`, :func:`bag_time_range`) and its message count
(:func:`message_count`). The IMU noise its messages declare comes with the reading
(``BagReport.imu_noise_declared``).

An indexed MCAP file answers from its summary (counts) and from the first and last chunk of
each topic (stamps), a few chunks instead of the whole file; an unindexed one is scanned with
the same vectorized scanner as the reader. Stamps are header stamps (s) where the type has a
header, else log times.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.records import ChunkIndex
from numpy.typing import NDArray

from pipe_nav_core.errors import BagError, BagFormatError
from pipe_nav_core.io.bagfiles import bag_layout, rosbag2_info
from pipe_nav_core.io.bagforms import Scanner, open_scanner, unpacked
from pipe_nav_core.io.mcapread import MessageBatch, chunk_messages, read_summary
from pipe_nav_core.io.stamps import NS_PER_S, ns_to_sec
from pipe_nav_core.io.topics import ROLE_TYPES, normalize_type


@dataclass
class TopicInfo:
    """One topic of a bag: type, message count and the first/last header stamp (s; the log
    time for types without a header)."""

    topic: str
    msgtype: str
    count: int
    start: float | None = None
    end: float | None = None


@dataclass
class BagInfo:
    """Cheap facts about a bag. ``indexed``: taken from the MCAP summaries (else by a scan);
    stamps then come from the first and last chunk of each topic."""

    path: str
    files: list[str]
    topics: dict[str, TopicInfo]
    message_count: int
    indexed: bool
    truncated: bool = False
    warnings: list[str] = field(default_factory=list)

    @property
    def start(self) -> float | None:
        v = [t.start for t in self.topics.values() if t.start is not None]
        return min(v) if v else None

    @property
    def end(self) -> float | None:
        v = [t.end for t in self.topics.values() if t.end is not None]
        return max(v) if v else None

    @property
    def duration(self) -> float:
        return (self.end - self.start) if self.start is not None and self.end is not None else 0.0


_HEADER_FIRST = "std_msgs/Header header"


def _has_header(schema_data: bytes, typename: str) -> bool:
    """Whether messages of this type start with a std_msgs/Header (known types by name, others
    by the first field of their ros2msg schema), i.e. whether a header stamp can be read."""
    if typename in ROLE_TYPES.values() or typename in (
        "nav_msgs/msg/Path",
        "diagnostic_msgs/msg/DiagnosticArray",
    ):
        return True
    for line in schema_data.decode("utf-8", "replace").splitlines():
        s = line.split("#", 1)[0].strip()
        if s:
            return " ".join(s.split()[:2]) in (_HEADER_FIRST, "std_msgs/msg/Header header")
    return False


def _stamps(batch: MessageBatch, sel: NDArray[np.int64], header: bool) -> NDArray[np.int64]:
    """Stamps (ns) of the messages ``sel``: the header stamp read straight from the CDR bytes
    (after the 4-byte encapsulation header), the log time for headerless types or payloads too
    short to hold one."""
    if not header:
        return batch.log_time[sel]
    starts = batch.payload_start[sel]
    ok = batch.size[sel] >= 12
    starts = np.where(ok, starts, 0)
    raw = batch.buf[(starts + 4)[:, None] + np.arange(8)]
    sec = raw[:, :4].copy().view("<i4").reshape(-1).astype(np.int64)
    nsec = raw[:, 4:].copy().view("<u4").reshape(-1).astype(np.int64)
    return np.where(ok, sec * NS_PER_S + nsec, batch.log_time[sel])


def bag_info(path: str | os.PathLike[str]) -> BagInfo:
    """Per-topic message counts, types and first/last header stamps, cheaply: from the MCAP
    summary (counts) and the first and last chunk of each topic (stamps) when the files are
    indexed, otherwise by scanning (slower, still vectorized)."""
    layout = bag_layout(path)
    files = [bf.path for bf in layout]
    topics: dict[str, TopicInfo] = {}
    warnings: list[str] = []
    indexed = True
    truncated = False
    total = 0

    def add(topic: str, typename: str, n: int, lo: int | None, hi: int | None) -> None:
        ti = topics.setdefault(topic, TopicInfo(topic, typename, 0))
        ti.count += n
        if lo is not None:
            s = float(ns_to_sec(lo))
            ti.start = s if ti.start is None else min(ti.start, s)
        if hi is not None:
            e = float(ns_to_sec(hi))
            ti.end = e if ti.end is None else max(ti.end, e)

    for bf in layout:
        f = bf.path
        if not f.is_file():
            warnings.append(f"{f}: missing")
            truncated = True
            continue
        try:
            summ = read_summary(f) if bf.plain_mcap else None
        except OSError as exc:
            raise BagError(f"{f}: cannot read ({exc.strerror or exc})") from None
        if summ is not None and summ.chunk_indexes:
            cache: dict[int, MessageBatch | None] = {}
            for cid, ch in summ.channels.items():
                sch = summ.schemas.get(ch.schema_id)
                typename = normalize_type(sch.name) if sch else ""
                header = _has_header(sch.data if sch else b"", typename)
                cis = [ci for ci in summ.chunk_indexes if cid in ci.message_index_offsets]
                n = 0
                if summ.channel_message_counts is not None:
                    n = summ.channel_message_counts.get(cid, 0)
                lo = hi = None
                if cis:
                    first = min(cis, key=lambda c: c.message_start_time)
                    last = max(cis, key=lambda c: c.message_end_time)
                    for ci, want in ((first, "lo"), (last, "hi")):
                        key = ci.chunk_start_offset
                        if key not in cache:
                            cache[key] = _chunk(f, ci)
                        b = cache[key]
                        if b is None:
                            continue
                        sel = np.flatnonzero(b.channel == cid)
                        if not len(sel):
                            continue
                        st = _stamps(b, sel, header)
                        if want == "lo":
                            lo = int(st.min())
                        else:
                            hi = int(st.max())
                    if summ.channel_message_counts is None:
                        n = 0
                        for ci in cis:
                            key = ci.chunk_start_offset
                            if key not in cache:
                                cache[key] = _chunk(f, ci)
                            b = cache[key]
                            n += 0 if b is None else int((b.channel == cid).sum())
                add(ch.topic, typename, n, lo, hi)
                total += n
            continue
        indexed = False
        try:
            with open_scanner(bf, warnings.append) as sc:
                total += _scan(sc, add)
                truncated |= sc.truncated
        except BagFormatError as exc:
            raise BagError(f"{f}: {exc}") from None
    return BagInfo(str(path), [str(f) for f in files], topics, total, indexed, truncated, warnings)


def _chunk(f: Path, ci: ChunkIndex) -> MessageBatch | None:
    """One indexed chunk's messages, their payloads decompressed where rosbag2 compressed
    each message."""
    b = chunk_messages(f, ci)
    return None if b is None else unpacked(b)


def _scan(sc: Scanner, add: Callable[[str, str, int, int | None, int | None], None]) -> int:
    """Every message of a file through ``add`` (topic, type, count, first and last stamp,
    ns) batch by batch; the number of messages."""
    total = 0
    for b in map(unpacked, sc.batches()):
        for cid in np.flatnonzero(np.bincount(b.channel)).tolist():
            ch = sc.channels.get(cid)
            if ch is None:
                continue
            sch = sc.schemas.get(ch.schema_id)
            typename = normalize_type(sch.name) if sch else ""
            sel = np.flatnonzero(b.channel == cid)
            st = _stamps(b, sel, _has_header(sch.data if sch else b"", typename))
            add(ch.topic, typename, len(sel), int(st.min()), int(st.max()))
            total += len(sel)
    return total


def message_count(path: str | os.PathLike[str]) -> int | None:
    """How many messages a bag holds, from its files' MCAP summaries or, for the other forms
    rosbag2 writes, from its metadata.yaml (without reading a message); None when they do not
    tell (a file without a summary, a form without metadata)."""
    layout = bag_layout(path)
    if all(bf.plain_mcap for bf in layout):
        total = 0
        for bf in layout:
            summary = read_summary(bf.path)
            if summary is None or summary.channel_message_counts is None:
                return None
            total += sum(summary.channel_message_counts.values())
        return total
    p = Path(path)
    try:
        return int(rosbag2_info(p if p.name == "metadata.yaml" else p / "metadata.yaml")
                   ["message_count"])  # fmt: skip
    except Exception:  # no metadata (a single file), or none that tells
        return None


def bag_time_range(
    path: str | os.PathLike[str], topics: Sequence[str] | None = None
) -> tuple[float, float] | None:
    """(first, last) header stamp in seconds over ``topics`` (default all), or None if empty."""
    info = bag_info(path)
    sel = [t for name, t in info.topics.items() if topics is None or name in topics]
    starts = [t.start for t in sel if t.start is not None]
    ends = [t.end for t in sel if t.end is not None]
    if not starts or not ends:
        return None
    return min(starts), max(ends)
