"""The per-topic checks of the bag reader: clock glitches, reordering, duplicates, late data.

One :class:`TopicState` per sensor topic takes the decoded samples in recording (file) order
and applies, vectorized over each batch:

1. an isolated stamp more than :data:`TIME_JUMP_S` ahead of both its neighbours is a clock
   glitch (``time_jump``); to judge the newest sample its successor is awaited (``pending``);
2. a stamp more than :data:`REORDER_WINDOW_S` behind the newest accepted stamp of its topic is
   dropped (``non_monotonic``), unless its log time is as far behind (a message the recorder
   wrote late, not a clock that stepped back); smaller disorder is repaired by sorting at
   :meth:`emit`, and so are the late writes;
3. after sorting, repeated stamps keep the first sample (``duplicate``);
4. streaming: a sample older than the boundary of a time chunk already handed out is dropped
   (``late``).

Markers only get duplicate removal (same name and stamp) and the late check.

This is not :class:`pipe_nav_core.filter.stream.ReorderBuffer`, although both reorder within a
window: that one orders single live samples of several kinds, each kind in its own sorted list,
in float seconds, and never drops a sample for being out of order (only for arriving after its
release); this one works on whole numpy batches of one topic in integer ns (1.5 M IMU samples
a run), drops what lies beyond the window and counts every reason in the :class:`BagReport`.
Sharing one would change what the reader keeps, or slow it by a Python step per sample.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.io.bagdecode import VALUE_KEYS, Pieces, empty_pieces
from pipe_nav_core.io.stamps import NS_PER_S
from pipe_nav_core.io.topics import (
    SKIP_DUPLICATE,
    SKIP_LATE,
    SKIP_NON_MONOTONIC,
    SKIP_TIME_JUMP,
    BagReport,
)
from pipe_nav_core.types import Marker

REORDER_WINDOW_S = 0.5  # s: stamps this much out of order are re-sorted, older ones dropped
TIME_JUMP_S = 1.0  # s: an isolated stamp this far ahead of both neighbours is a glitch


@dataclass
class TopicState:
    """The checks and the buffer of one topic (``role``: imu, odometer, mag or markers); the
    skips are counted in ``report``, the samples handed out in ``report.counts``. Stamps in
    integer ns."""

    topic: str
    role: str
    report: BagReport
    run_max: int | None = None  # newest accepted stamp, ns
    run_max_log: int | None = None  # newest log time met, ns (where the bag gives them)
    prev_ns: int | None = None  # stamp of the previous message in arrival order
    pending: Pieces | None = None  # last message, held for the time-jump test
    buffer: list[Pieces] = field(default_factory=list)
    boundary: int | None = None  # stamps below this were handed out already (streaming)
    last_emitted: int | None = None
    emitted_markers: set[tuple[str, int]] = field(default_factory=set)
    seen: int = 0  # messages of the topic met in the bag (before any check)

    @property
    def keys(self) -> tuple[str, ...]:
        """The value columns of this role's samples."""
        return VALUE_KEYS[self.role]

    def ingest(self, p: Pieces, final: bool = False) -> None:
        """Add decoded, finite samples (arrival order)."""
        if self.role == "markers":
            self._ingest_markers(p)
            return
        if self.pending is not None:
            p = Pieces.concat([self.pending, p], self.keys) if len(p) else self.pending
            self.pending = None
        if len(p) == 0:
            return
        ns = p.ns
        m = len(ns)
        jump = np.int64(int(TIME_JUMP_S * NS_PER_S))
        prev = np.empty(m, dtype=np.int64)
        prev[1:] = ns[:-1]
        prev[0] = ns[0] if self.prev_ns is None else self.prev_ns
        hold_last = not final
        nxt = np.empty(m, dtype=np.int64)
        nxt[:-1] = ns[1:]
        nxt[-1] = ns[-1]  # the last one is decided with the next batch (or accepted at the end)
        ahead_of_prev = ns - prev > jump
        if self.prev_ns is None:
            ahead_of_prev[0] = True  # the very first message: judged by its successor only
        spike = ahead_of_prev & (ns - nxt > jump)
        if hold_last:
            self.pending = p.take(slice(m - 1, m))
            keep_n = m - 1
        else:
            keep_n = m
        self.prev_ns = int(ns[keep_n - 1]) if keep_n > 0 else self.prev_ns
        if keep_n == 0:
            return
        spike = spike[:keep_n]
        ns = ns[:keep_n]
        if spike.any():
            self.report.add_skipped(self.topic, SKIP_TIME_JUMP, int(spike.sum()))
        # Running maximum over everything before each sample (spikes excluded).
        ns_f = np.where(spike, np.iinfo(np.int64).min, ns)
        cm = np.maximum.accumulate(ns_f)
        before = np.empty(keep_n, dtype=np.int64)
        before[0] = np.iinfo(np.int64).min
        before[1:] = cm[:-1]
        if self.run_max is not None:
            before = np.maximum(before, self.run_max)
        window = np.int64(int(REORDER_WINDOW_S * NS_PER_S))
        lo = np.where(before == np.iinfo(np.int64).min, before, before - window)
        accept = ~spike & (ns > lo)
        if p.log is not None:
            log = p.log[:keep_n]
            if not (accept | spike).all():  # only a batch with stamps out of the window
                accept |= ~spike & ~accept & self._written_late(log, ns, before, window)
            newest = int(log.max())
            self.run_max_log = newest if self.run_max_log is None else max(self.run_max_log, newest)
        n_back = int((~spike & ~accept).sum())
        if n_back:
            self.report.add_skipped(self.topic, SKIP_NON_MONOTONIC, n_back)
        if self.boundary is not None:
            dup = accept & (ns == self.last_emitted) if self.last_emitted is not None else None
            if dup is not None and dup.any():
                self.report.add_skipped(self.topic, SKIP_DUPLICATE, int(dup.sum()))
                accept &= ~dup
            late = accept & (ns < self.boundary)
            if late.any():
                self.report.add_skipped(self.topic, SKIP_LATE, int(late.sum()))
                accept &= ~late
        if cm.size and cm[-1] != np.iinfo(np.int64).min:
            top = int(cm[-1])
            self.run_max = top if self.run_max is None else max(self.run_max, top)
        idx = np.flatnonzero(accept)
        kept = p.take(slice(0, keep_n) if len(idx) == keep_n else idx)  # all: views, not copies
        if len(kept):
            kept.log = None  # judged: the buffer holds the stamps and values only
            self.buffer.append(kept)

    def _written_late(
        self,
        log: NDArray[np.int64],
        ns: NDArray[np.int64],
        before: NDArray[np.int64],
        window: np.int64,
    ) -> NDArray[np.bool_]:
        """Which samples' log times are behind the newest log time before them by as much as
        their stamps are behind the newest stamp (less the window): messages the recorder
        wrote late (rosbag2's message compression does so under load, a second or more after
        their neighbours), not a clock that stepped back (its log times go on). Sorted into
        place at :meth:`emit` like the smaller disorder."""
        low = np.iinfo(np.int64).min
        seen = np.maximum.accumulate(log)
        log_before = np.empty(len(log), dtype=np.int64)
        log_before[0] = low if self.run_max_log is None else self.run_max_log
        log_before[1:] = np.maximum(seen[:-1], log_before[0])
        known = (log_before != low) & (before != low)
        late = np.zeros(len(log), dtype=bool)
        late[known] = (log_before[known] - log[known]) >= (before[known] - ns[known] - window)
        return late

    def _ingest_markers(self, p: Pieces) -> None:
        """Markers: only the late check here (duplicates are removed at emit), with a warning
        naming each late marker, since a lost marker moves the whole trajectory."""
        if len(p) == 0:
            return
        if self.boundary is not None:
            late = p.ns < self.boundary
            for i in np.flatnonzero(late):
                mk: Marker = p.values["marker"][i]
                self.report.add_skipped(self.topic, SKIP_LATE)
                self.report.warn(
                    f"{self.topic}: marker {mk.name!r} (t={mk.t:.3f} s) arrived after its time "
                    "chunk was handed out and was dropped; read the whole bag or give the "
                    "markers as a CSV file"
                )
            p = p.take(np.flatnonzero(~late))
        if len(p):
            self.buffer.append(p)

    def flush_pending(self) -> None:
        """At the end of the bag: judge the held-back last sample (it has no successor)."""
        if self.pending is not None:
            p, self.pending = self.pending, None
            self.ingest(p, final=True)

    def high_water(self) -> int | None:
        """The newest accepted stamp (ns), or None before any."""
        return self.run_max

    def emit(self, upto: int | None) -> Pieces:
        """Sorted, de-duplicated samples with stamp < upto (all when None)."""
        if not self.buffer:
            if upto is not None:
                self.boundary = upto if self.boundary is None else max(self.boundary, upto)
            return empty_pieces(self.role)
        parts, self.buffer = self.buffer, []
        one = len(parts) == 1  # then concat gives the piece itself: views of a decoded chunk
        allp = Pieces.concat(parts, self.keys)
        del parts  # the pieces go as soon as they are joined (a 100 km IMU is 0.6 GB)
        if one or np.any(allp.ns[1:] < allp.ns[:-1]):  # copied in stamp order (stable)
            allp = allp.take(np.argsort(allp.ns, kind="stable"))
        if upto is None:
            out, rest = allp, None
        else:
            cut = int(np.searchsorted(allp.ns, upto, side="left"))
            out = allp.take(np.arange(cut))
            rest = allp.take(np.arange(cut, len(allp))) if cut < len(allp) else None
        self.buffer = [rest] if rest is not None and len(rest) else []
        if self.role == "markers":
            keep = []
            for i, mk in enumerate(out.values["marker"]):
                key = (mk.name, int(out.ns[i]))
                if key in self.emitted_markers:
                    self.report.add_skipped(self.topic, SKIP_DUPLICATE)
                    continue
                self.emitted_markers.add(key)
                keep.append(i)
            out = out.take(np.asarray(keep, dtype=np.int64))
        elif len(out):
            dup = np.zeros(len(out), dtype=bool)
            dup[1:] = out.ns[1:] == out.ns[:-1]
            if self.last_emitted is not None:
                dup[0] = out.ns[0] == self.last_emitted
            if dup.any():
                self.report.add_skipped(self.topic, SKIP_DUPLICATE, int(dup.sum()))
                out = out.take(np.flatnonzero(~dup))
            if len(out):
                self.last_emitted = int(out.ns[-1])
        if upto is not None:
            self.boundary = upto if self.boundary is None else max(self.boundary, upto)
        self.report.counts[self.topic] = self.report.counts.get(self.topic, 0) + len(out)
        return out
