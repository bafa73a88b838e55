"""The first smoothing pass run while the bag is still being read.

The reading (:func:`pipe_nav_core.io.read_bag` with ``pieces``) hands the run over in time
chunks; a thread here runs on them what :func:`.passes.smooth_log` runs first: the IMU model
chosen from the static spans read so far, the heading search once the data reach the second
marker, then the first filter pass over the chunks as they come. The passes are sequential
and the reading keeps one core busy, so the two overlap on a machine of two cores.

It is a guess about the run: :meth:`FirstPassAhead.take` gives the pass to smooth_log only
where smooth_log would have run exactly this pass (the very log that was read, unrepaired,
with the same markers, the same configuration before the heading search, the same method,
forward in time); otherwise the pass is dropped and smooth_log runs its own. Either way the
result is the same, bit for bit (tested); a guess that fails costs CPU, not answers.
"""

from __future__ import annotations

import queue
import threading

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.navigator import Navigator, PassOptions
from pipe_nav_core.io import BagReport, concat_logs
from pipe_nav_core.model import imu_noise as imu_model
from pipe_nav_core.smooth.heading import PAST_SECOND_MARKER_S, smoothing_config
from pipe_nav_core.smooth.passes import epoch_config
from pipe_nav_core.types import Marker, SensorLog, markers_sorted

_END = None  # the queue's last item: the reading is over (or failed)


class FirstPassAhead:
    """The heading search and the first filter pass of ``method`` over a bag being read, in
    a thread of its own. Call it with each time chunk and the report so far (the reader's
    ``pieces``), then :meth:`finish` with the log read (or :meth:`cancel`), then :meth:`take`;
    as a context, its thread is stopped at the end.
    ``config``: the settings smooth_log is given (imu_grade auto is resolved here as
    :func:`pipe_nav_core.model.imu_noise.choose` resolves it, from the data read so far)."""

    def __init__(self, config: NavConfig, method: str) -> None:
        self.config = config
        self.method = method
        self._inbox: queue.SimpleQueue[tuple[SensorLog, BagReport] | None] = queue.SimpleQueue()
        self._log: SensorLog | None = None  # the log read, as finish() was given it
        self._markers: list[Marker] = []
        self._result: tuple[NavConfig, NavConfig, Navigator] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pipe-nav first pass",
                                        daemon=True)  # fmt: skip
        self._thread.start()

    def __enter__(self) -> FirstPassAhead:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()
        self._thread.join()  # nothing of it outlives the run (it stops at its next chunk)

    def __call__(self, piece: SensorLog, report: BagReport) -> None:
        self._inbox.put((piece, report))

    def finish(self, log: SensorLog) -> None:
        """The reading is over: ``log`` is what it read (the chunks concatenated)."""
        self._log = log
        self._markers = list(log.markers)
        self._inbox.put(_END)

    def cancel(self) -> None:
        """Stop the thread (the reading failed, or no one will take the pass)."""
        self._stop.set()
        self._inbox.put(_END)

    def take(
        self, log: SensorLog, config: NavConfig, method: str, reverse: bool
    ) -> tuple[NavConfig, Navigator] | None:
        """(the configuration after the heading search, the first pass) when smooth_log's
        first pass over ``log`` with ``config`` (before the heading search) and ``method``
        would be this one; else None. Waits for the thread; gives the pass at most once."""
        self._thread.join()
        result, self._result = self._result, None
        if result is None or reverse or method != self.method:
            return None
        given, anchored, nav = result
        if log is not self._log or log.markers != self._markers or config != given:
            return None
        return anchored, nav

    def _run(self) -> None:
        try:
            self._result = self._pass(_Chunks(self._inbox, self._stop))
        except Exception:  # noqa: BLE001 - smooth_log runs the pass itself and meets it again
            self._result = None
        finally:
            self._stop.set()
            while not self._inbox.empty():  # let go of what was not read
                self._inbox.get()

    def _pass(self, chunks: _Chunks) -> tuple[NavConfig, NavConfig, Navigator] | None:
        # up to the second marker and PAST_SECOND_MARKER_S beyond (what the search reads)
        while not chunks.past_second_marker():
            if not chunks.more():
                break
        if self._stop.is_set():
            return None
        head = concat_logs(chunks.read)
        if len(head.imu) < 10:
            return None
        choice = imu_model.choose(head, self.config, chunks.report.imu_noise_declared or None)
        given = epoch_config(choice.config, self.method)
        anchored = given if self.method == "forward" else smoothing_config(head, given)
        del head
        nav = Navigator(anchored, markers_sorted(chunks.markers()),
                        PassOptions(record=True, emit=False))  # fmt: skip
        fed = 0
        while True:
            while fed < len(chunks.read) - 1:  # the last chunk waits: it may be the final one
                if self._stop.is_set():
                    return None
                nav.run(chunks.read[fed], final=False)
                chunks.read[fed] = _EMPTY  # the log keeps its own copy
                fed += 1
            if not chunks.more():
                break
        if self._stop.is_set():
            return None
        nav.run(chunks.read[fed] if fed < len(chunks.read) else _EMPTY, final=True)
        if nav.state is None or nav.recording is None:
            return None
        nav.recording.trim()
        return given, anchored, nav


_EMPTY = SensorLog()


class _Chunks:
    """The time chunks read so far, and the wait for the next."""

    def __init__(
        self,
        inbox: queue.SimpleQueue[tuple[SensorLog, BagReport] | None],
        stop: threading.Event,
    ) -> None:
        self.inbox, self.stop = inbox, stop
        self.read: list[SensorLog] = []
        self.report = BagReport()
        self.done = False

    def more(self) -> bool:
        """Wait for the next chunk: False at the end of the reading (done) or when stopped."""
        if self.done or self.stop.is_set():
            return False
        item = self.inbox.get()
        if item is _END:
            self.done = True
            return False
        piece, self.report = item
        self.read.append(piece)
        return True

    def markers(self) -> list[Marker]:
        return [m for p in self.read for m in p.markers]

    def past_second_marker(self) -> bool:
        """Whether the chunks read reach PAST_SECOND_MARKER_S beyond the second marker."""
        ms = markers_sorted(self.markers())
        last = max((float(p.imu.t[-1]) for p in self.read if len(p.imu)), default=None)
        return len(ms) >= 2 and last is not None and last >= ms[1].t + PAST_SECOND_MARKER_S
