"""Where the filter's epochs end, and their inputs to the compiled epoch loop.

An epoch ends at the first IMU sample at or after the previous end plus the filter period
(``filter_rate_hz``), or at the epoch times a smoother pass imposes, and is cut at a marker
passage, whose epoch runs alone (the navigator re-anchors the heading between its prediction
and its updates). An epoch runs only once all its data are in (the reorder horizon), and waits
up to ODOMETER_TIMEOUT_S for the odometer. The epochs run compiled
(:mod:`pipe_nav_core.filter.epoch`),
as many per call as the buffered data allow (at most MAX_BATCH: one at a time live, thousands
offline; the results do not depend on it).
"""

from __future__ import annotations

import math
from collections import defaultdict
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.filter.epoch import COUNTERS, KINDS, Batch, Inputs
from pipe_nav_core.filter.ingest import STOP_MARGIN_S
from pipe_nav_core.filter.kalman import UpdateStats
from pipe_nav_core.jit import kernel

if TYPE_CHECKING:
    from pipe_nav_core.filter.ingest import Inbox
    from pipe_nav_core.filter.odometer_resolution import OdometerResolution

Array = NDArray[np.float64]
Ends = NDArray[np.int64]  # per epoch, the index of its last IMU sample in the buffer

ODOMETER_TIMEOUT_S = 1.0  # an epoch waits at most this long (stamp time) for odometer coverage
MAX_BATCH = 1024  # epochs per call of the compiled epoch loop (bounds its output buffers)
SAMPLES_PER_EPOCH = 20  # IMU samples per epoch the shared output buffers are first sized for


def plan(
    inbox: Inbox, t0: float, period: float, epoch_times: Array | None, stop_speed: float
) -> tuple[Ends, bool, NDArray[np.bool_]]:
    """The next epochs after the state's time t0 (s) over the buffered data, with the filter
    period (s) or the imposed epoch_times (s, sorted): their last IMU samples (indices into
    the buffer), at most MAX_BATCH, whether the last of them is a marker passage's epoch
    (then it is the only one with a marker due), and per epoch whether the odometer stands
    still over it and STOP_MARGIN_S either side, where a stop may be claimed (:func:`stops`;
    stop_speed m/s; :func:`epoch_inputs` takes it). An epoch over which the odometer has stood
    still so far waits for the readings STOP_MARGIN_S after it, which decide that; a moving
    pig's epochs do not wait. One answer decides both, so they cannot disagree."""
    times = epoch_times if epoch_times is not None else np.empty(0)
    mk = np.array([m.t for m in inbox.markers]) if inbox.markers else np.empty(0)
    odo_end = float(inbox.odo.t[-1]) if len(inbox.odo) else -math.inf
    ends, due = _plan_epochs(
        inbox.imu_t, t0, period, times, mk, inbox.horizon, odo_end, ODOMETER_TIMEOUT_S, MAX_BATCH
    )
    still = np.zeros(len(ends), dtype=bool)
    if len(ends) and len(inbox.odo):
        t_end = inbox.imu_t[ends]
        so_far, decided, still = stops(inbox, np.r_[t0, t_end[:-1]], t_end, stop_speed)
        wait = so_far & ~decided
        if wait.any():
            k = int(np.argmax(wait))
            ends, due, still = ends[:k], False, still[:k]  # a marker's epoch, if due, was last
    return ends, due, still


def stops(
    inbox: Inbox, t_start: Array, t_end: Array, stop_speed: float
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """Per epoch from t_start to t_end (s), with the odometer's buffered readings: whether the
    count has stood still from STOP_MARGIN_S before the epoch to its end (a mean speed under
    stop_speed, m/s); whether what follows is known (a reading from STOP_MARGIN_S after it on
    is in, or the data to ODOMETER_TIMEOUT_S past that, or the log has ended); and whether it
    stands still over the whole span, read on the first reading after it (within
    ODOMETER_TIMEOUT_S, or the log's last): where a stop may be claimed. The same data give
    the same answers however they were batched."""
    o = inbox.odo
    lo, hi = t_start - STOP_MARGIN_S, t_end + STOP_MARGIN_S
    s_lo = np.interp(lo, o.t, o.distance)
    so_far = np.abs(np.interp(t_end, o.t, o.distance) - s_lo) <= stop_speed * (t_end - lo)
    j = np.searchsorted(o.t, hi, side="left")
    after = j < len(o.t)
    ended = inbox.horizon == math.inf
    decided = after | (inbox.horizon >= hi + ODOMETER_TIMEOUT_S) | ended
    first = o.t[np.minimum(j, len(o.t) - 1)]
    seen = (after & (first - hi <= ODOMETER_TIMEOUT_S)) | (~after & ended)
    moved = np.abs(np.interp(hi, o.t, o.distance) - s_lo)
    return so_far, decided, so_far & seen & (moved <= stop_speed * (hi - lo))


def epoch_inputs(
    inbox: Inbox,
    t0: float,
    ends: Ends,
    odometer_exclude: Array,
    resolution: OdometerResolution,
    still: NDArray[np.bool_],
) -> Inputs:
    """The data of the epochs after t0 (s) ending at these IMU samples: the samples, per epoch
    the odometer coverage, excluded (inside one of the odometer_exclude intervals (N, 2) s:
    slips), encoder resolution (m) and magnetometer sample, per IMU sample the odometer
    reading (m); ``still``, per epoch, is :func:`plan`'s (the odometer stands still over it and
    STOP_MARGIN_S either side: a stop may be claimed where it also covers the epoch)."""
    t = inbox.imu_t[: ends[-1] + 1]
    t_end = t[ends]
    t_start = np.r_[t0, t_end[:-1]]
    o = inbox.odo
    s_odo = inbox.odometer_at(t)
    if len(o):
        # readings around the epoch, neither over ODOMETER_TIMEOUT_S away: across a longer
        # silence (a dropout, a stuck wheel's readings left out) the count interpolated
        # between its ends is not a measurement
        before = o.t[np.maximum(np.searchsorted(o.t, t_start, side="right") - 1, 0)]
        after = o.t[np.minimum(np.searchsorted(o.t, t_end, side="left"), len(o.t) - 1)]
        has_odo = ((o.t[-1] >= t_end) & (before <= t_start + 1e-9)
                   & (t_start - before <= ODOMETER_TIMEOUT_S)
                   & (after - t_end <= ODOMETER_TIMEOUT_S))  # fmt: skip
    else:
        has_odo = np.zeros(len(ends), dtype=bool)
    ex = odometer_exclude
    excluded = np.zeros(len(ends), dtype=bool)
    if len(ex):
        # some interval starts before the epoch's end and ends after its start
        lo = np.searchsorted(ex[:, 0], t_end)
        latest_end = np.maximum.accumulate(ex[:, 1])[np.maximum(lo - 1, 0)]
        excluded = (lo > 0) & (latest_end > t_start)
    mag = inbox.mag
    mag_i = np.searchsorted(mag.t, t_end, side="right") - 1
    ok = mag_i >= 0
    ok[ok] = mag.t[mag_i[ok]] > t_start[ok] + 1e-9
    mag_i = np.where(ok, mag_i, -1)
    res = resolution.at_times(o, t_end)
    n = ends[-1] + 1
    return Inputs(
        inbox.imu_t[:n], inbox.imu_g[:n], inbox.imu_a[:n], ends, s_odo, has_odo, still, excluded,
        res, mag_i, mag.t, mag.field,
    )  # fmt: skip


class BatchPool:
    """The compiled loop's output buffers (n: error states), reused from batch to batch
    (fresh memory costs page faults); with double, two in turn, the recording packing one's
    covariances in a second thread while the next batch runs (Recording.add_epochs); with
    transitions, a transition row per epoch (Batch)."""

    def __init__(self, n: int, double: bool, transitions: bool = False) -> None:
        self.n = n
        self.double = double
        self.transitions = transitions
        self._batches: list[Batch | None] = [None, None]
        self._turn = 0

    def get(self, epochs: int, samples: int) -> Batch:
        """Buffers for this many epochs and IMU samples, cleared."""
        if self.double:
            self._turn ^= 1
        b = self._batches[self._turn]
        if b is None or len(b.sv) < epochs or len(b.lat) < samples:
            size = max(epochs, MAX_BATCH if self.double else 1)
            b = Batch(size, max(samples, 2 * size * SAMPLES_PER_EPOCH), self.n,
                      transitions=self.transitions)  # fmt: skip
            self._batches[self._turn] = b
        b.reset()
        return b


def tally(batch: Batch, counts: defaultdict[str, int], stats: UpdateStats) -> None:
    """A batch's event counters into counts, its updates (accepted, rejected, NIS) into
    stats."""
    for name, c in zip(COUNTERS, batch.counts, strict=True):
        if c:
            counts[name] += int(c)
    for k, name in enumerate(KINDS):
        if batch.acc[k] or batch.rej[k]:
            stats.accepted[name] += int(batch.acc[k])
            stats.rejected[name] += int(batch.rej[k])
            stats.nis_sum[name] += float(batch.nis[k])
            stats.dof_sum[name] += int(batch.dof[k])


@kernel
def _plan_epochs(
    t: Array,
    t0: float,
    period: float,
    epoch_times: Array,
    markers: Array,
    horizon: float,
    odo_end: float,
    timeout: float,
    max_epochs: int,
) -> tuple[NDArray[np.int64], bool]:
    """:func:`plan`'s epochs: they end at the first sample of t (s) at or after t_prev +
    period (or at the given epoch_times), cut at the first pending marker passage (markers:
    sorted times, s); an epoch waits for its samples (horizon s: stamp time up to which all
    data are in) and, up to timeout s, for odometer coverage (odo_end: the last odometer
    stamp). Returns the ends and whether the last epoch has a marker due (planning stops there)."""
    ends = np.empty(max_epochs, dtype=np.int64)
    nb = 0
    t_prev = t0
    due = False
    while nb < max_epochs:
        if epoch_times.shape[0] > 0:
            i = np.searchsorted(epoch_times, t_prev + 1e-9, side="right")
            target = epoch_times[i] - 1e-9 if i < epoch_times.shape[0] else np.inf
            end = np.searchsorted(t, target)
        else:
            end = np.searchsorted(t, t_prev + period - 1e-9)
            j = np.searchsorted(markers, t_prev, side="right")  # the first pending marker
            if j < markers.shape[0]:
                end = min(end, np.searchsorted(t, markers[j]))
        if end >= t.shape[0]:
            break
        t_end = t[end]
        if horizon < t_end or (odo_end < t_end and horizon < t_end + timeout):
            break
        ends[nb] = end
        nb += 1
        t_prev = t_end
        if markers.shape[0] > 0 and markers[0] <= t_end:
            due = True
            break
    return ends[:nb], due
