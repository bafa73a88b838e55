"""Time ordering of samples from several topics that may arrive out of order.

Samples are held for ``window`` seconds of stamp time and released in stamp order; a sample
older than what was already released is late: it is counted and dropped.

Each topic arrives in its own order but the topics need not keep pace with one another: behind
a backlog (a node that fell behind, a driver with a longer latency) one topic's samples can
reach the buffer over ``window`` after another's of the same stamps. So a sample is also held
until every stream (``STREAMS``) still sending has passed its stamp: only a stream silent for
over ``hold`` seconds of stamp time (a dropout, a sensor that is not there) holds nothing back.
A stream further behind than ``hold`` is still waited for, up to ``MAX_BACKLOG_S``, while its
samples keep arriving (one within ``SILENT_S`` of wall time in which others came; a pause of
every input, ``PAUSE_S`` or more, is not a silence): behind a node that was stalled, the
topics' backlogs come back at their own pace (a reliable writer resends what the reader missed,
each topic on its own; an executor serves the queues a message each in turn), so the fastest
topic falls behind the others by most of the stall's worth of stamp time (tens of seconds
under a replay at 10x), and comes in bursts.
The released order, and so every result, is the same; what changes is only when samples leave,
and which ones would otherwise be late.
"""

from __future__ import annotations

import bisect
import math
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

STREAMS = ("imu", "odometer", "mag")  # the kinds whose stamps come steadily (not markers)
HOLD_S = 5.0  # s of stamp time a lagging stream is waited for, arriving or not
MAX_BACKLOG_S = 60.0  # s of stamp time a lagging stream is waited for while it arrives
SILENT_S = 5.0  # s of wall time (``clock``) without a sample: a stream is not arriving
PAUSE_S = 1.0  # s of wall time without any sample pushed: not counted as any stream's silence

Released = dict[str, tuple[list[float], list[Any]]]  # per kind: stamps (s) and payloads


class ReorderBuffer:
    """Puts pushed samples of several kinds in stamp order.

    window: s, how far behind the newest stamp a sample may arrive; hold: s, how far a
    lagging stream's newest stamp may be behind the newest of all and still hold the release
    back; backlog: s, as hold for a stream still arriving (see the module docstring);
    clock: wall time (s) that says whether a stream is still arriving.

    Each kind is kept in its own stamp-sorted list (a sample arriving in its kind's order,
    the common case, is appended) and released per kind: every sample of one release is
    stamped at or before every sample of the next.
    """

    def __init__(
        self,
        window: float,
        hold: float = HOLD_S,
        backlog: float = MAX_BACKLOG_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.window = float(window)
        self.hold = max(float(hold), self.window)
        self.backlog = max(float(backlog), self.hold)
        self._t: defaultdict[str, list[float]] = defaultdict(list)  # s, per kind, sorted
        self._p: defaultdict[str, list[Any]] = defaultdict(list)  # payloads, as _t
        self._held = 0
        self.newest = -math.inf
        self._newest_of = dict.fromkeys(STREAMS, -math.inf)  # s, per stream
        self._clock = clock
        self._arrived = dict.fromkeys(STREAMS, -math.inf)  # per stream, clock at its latest
        self._pushed = -math.inf  # clock at the latest push
        self.horizon = -math.inf  # everything stamped at or before it has been released
        self.late: dict[str, int] = defaultdict(int)

    def push(self, t: float, kind: str, payload: Any) -> bool:
        """Add one sample; False (and counted) if it is older than the release horizon."""
        if t <= self.horizon:
            self.late[kind] += 1
            return False
        ts = self._t[kind]
        if ts and t < ts[-1]:  # out of its kind's order; after the samples of equal stamp
            i = bisect.bisect_right(ts, t)
            ts.insert(i, t)
            self._p[kind].insert(i, payload)
        else:
            ts.append(t)
            self._p[kind].append(payload)
        self._held += 1
        now = self._clock()
        pause = now - self._pushed
        if PAUSE_S <= pause < math.inf:  # every input stood still: no stream's silence
            for k in self._arrived:
                self._arrived[k] += pause
        self._pushed = now
        if kind in self._arrived:
            self._arrived[kind] = now
        if t > self.newest:
            self.newest = t
        if kind in self._newest_of and t > self._newest_of[kind]:
            self._newest_of[kind] = t
        return True

    def release(self, flush: bool = False) -> Released:
        """Per kind, in stamp order, the samples at least ``window`` older than the newest
        and not ahead of any stream still sending (all of them when flush); kinds with none
        left out."""
        cutoff = math.inf if flush else self._cutoff()
        out: Released = {}
        for kind, ts in self._t.items():
            i = bisect.bisect_right(ts, cutoff)
            if i:
                p = self._p[kind]
                out[kind] = (ts[:i], p[:i])
                del ts[:i], p[:i]
                self._held -= i
        if cutoff > self.horizon:
            self.horizon = cutoff
        return out

    def _cutoff(self) -> float:
        """s: the stamp up to which samples may leave (module docstring)."""
        cutoff = self.newest - self.window
        lagging, backlog = self.newest - self.hold, self.newest - self.backlog
        for kind, t in self._newest_of.items():
            if backlog <= t < cutoff and (
                t >= lagging or self._clock() - self._arrived[kind] <= SILENT_S
            ):
                cutoff = t
        return cutoff

    def __len__(self) -> int:
        return self._held
