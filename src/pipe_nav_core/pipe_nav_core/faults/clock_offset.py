"""The IMU's clock against the odometer's: an offset between their stamps, constant or
drifting, measured where the pig sets off and comes to rest, and taken out.

Two drivers on two clocks (an IMU stamping its samples with its own counter, a wheel encoder
with the host's, or a USB latency one of them does not take off) put the same motion at two
times; two free-running crystals 50 ppm apart drift 0.27 s apart over a 10 km run. The filter
then reads each odometer increment against the wrong IMU samples: 50 ms cost the bundled
sample 5 cm, 0.2 s cost it 2.6 m and a marker falsely left out.

Where the pig sets off after a rest (or comes to rest before one) of ``REST_MIN_S`` (the
odometer still: :func:`pipe_nav_core.model.imu_noise.static_spans`), the specific force along
the pig's axis (imu_link -> base_link by the configured mount) less its mean at rest,
integrated twice from the rest, is the distance the pig moved since (or until) then. Each
change of the wheel's count is the distance crossing the new reading, between two readings
(their middle). For each lag of the IMU's stamps within ``SEARCH_S`` (``STEP_S``, then
``FINE_S`` about the best) the two distances are fitted by a scale (the wheel's, within
``SCALE_RANGE``) and a constant (where the count stood at rest); the lag of the least misfit is
that event's offset. On simulated runs of the test pipes, the 1.5 km lines and the sample, an
event's offset is within 35 ms of the truth, a few 0.06-0.15 s off where the pig pitched as it
set off: those fit worse, and events fitting ``REJECT_FACTOR`` times worse than the run's
median event are left out.

The events (the ``MAX_EVENTS`` longest rests') give one offset where most of them agree on it
within ``AGREE_S``, else a steady drift where most lie within AGREE_S of one line over time;
each weighted by the inverse square of its misfit (:func:`_model`). It is taken out where it
reaches ``MIN_OFFSET_S`` (``ONE_EVENT_MIN_S`` on the word of a single event) and half the
events or more agree on it: the IMU's and the magnetometer's stamps are moved onto the
odometer's clock (the magnetometer is in imu_link, the IMU's own chip: INTERFACES.md). Where
neither explains the events (they lie ``IRREGULAR_S`` apart), or one of them lies that far from
what does (the clock changed within the run), it is named and nothing is moved. The
odometer's clock is kept: the markers' passages and the outputs' ``time_s`` are on it.

Times s (header stamps), distances m, specific force m/s^2.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.model.imu_noise import static_spans
from pipe_nav_core.types import ImuSamples, MagSamples, SensorLog

REST_MIN_S = 2.0  # s: the shortest rest an event needs (the odometer still)
REST_S = 3.0  # s of the rest averaged for the specific force at rest
MARGIN_S = 1.0  # s of the rest left out next to the motion (the pig creeps before a count)
MOTION_S = 4.0  # s of motion fitted after a start, before a stop
SEARCH_S = 10.0  # s: offsets searched either way
STEP_S = 0.02  # s: the search's step
FINE_S = 0.002  # s: the step about the best of the search
MIN_CROSSINGS = 10  # changes of the count an event needs within MOTION_S
MIN_REST_SAMPLES = 20  # IMU samples the rest's mean needs
SCALE_RANGE = (0.75, 1.35)  # odometer distance per IMU distance of a sound fit
REJECT_FACTOR = 1.8  # an event whose misfit is this many times the median event's is left out
MAX_EVENTS = 8  # events measured (the longest rests)
MIN_OFFSET_S = 0.03  # s: an offset taken out when two events or more agree on it
ONE_EVENT_MIN_S = 0.25  # s: one taken out on the word of a single event
AGREE_S = 0.05  # s: events within this of the offset (or of the drift's line) agree
MIN_DRIFT_SPAN_S = 300.0  # s: the events a drift is fitted to span at least this
MIN_DRIFT_EVENTS = 4  # events a drift needs to agree on it
IRREGULAR_S = 0.25  # s: an event this far off the offset (or the events this far apart) is a
# clock that changed (events that pitched as the pig set off were 0.06-0.15 s off)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ClockOffset:
    """The IMU's stamps minus the odometer's for the same motion (s; positive: the IMU's are
    late): ``seconds`` at odometer time ``t_ref`` (s), changing by ``rate`` (s/s: a clock
    that drifts) away from it, measured at ``events`` starts and stops of the pig that agree
    on it within AGREE_S. ``first`` and ``last``: the offset at the IMU's first and last
    stamps (s). ``retime``: it is to be taken out; ``irregular``: the events disagree beyond
    IRREGULAR_S and neither an offset nor a drift explains them (nothing is moved)."""

    seconds: float
    rate: float
    t_ref: float
    first: float
    last: float
    events: int
    retime: bool
    irregular: bool = False

    def at(self, t: Array) -> Array:
        """The offset (s) at times ``t`` (s)."""
        return self.seconds + self.rate * (t - self.t_ref)

    @property
    def named(self) -> bool:
        """Whether it is to be said: taken out, or no offset explains the events."""
        return self.retime or self.irregular

    def describe(
        self, done: str = "the IMU and the magnetometer re-timed to the odometer's clock"
    ) -> str:
        """One line for people; ``done``: what was done about it (where it is retimed)."""
        ms = f"{1e3 * self.first:+.0f} to {1e3 * self.last:+.0f} ms"
        if self.irregular:
            return (
                f"IMU clock: its stamps are {ms} off the odometer's at {self.events} starts and "
                "stops of the pig, neither one offset nor a steady drift: not re-timed"
            )
        where = (f"{self.events} starts and stops of the pig" if self.events > 1
                 else "the one start or stop of the pig")  # fmt: skip
        if self.rate:
            what = (f"drift from {ms} off the odometer's over the run ({1e6 * self.rate:+.0f} "
                    "ppm)")  # fmt: skip
        else:
            way = "later" if self.seconds > 0 else "earlier"
            what = f"are {1e3 * abs(self.seconds):.0f} ms {way} than the odometer's"
        return f"IMU clock: its stamps {what} for the same motion (measured at {where}): {done}"


def measure(log: SensorLog, mount: Array) -> ClockOffset | None:
    """The offset of the IMU's stamps from the odometer's in ``log`` (``mount``: (3, 3)
    imu_link -> base_link), or None where no start or stop of the pig can be measured."""
    events = _events(log)
    found = np.array([e for e in (_event(log, mount, *ev) for ev in events) if e])
    if not len(found):
        return None
    misfit = found[:, 3]
    sound = misfit <= REJECT_FACTOR * float(np.median(misfit))
    t, lag, weight = found[sound, 0], found[sound, 1], misfit[sound] ** -2.0
    model = _model(t, lag, weight)
    if model is None or np.max(np.abs(lag - model[0] - model[1] * (t - model[2]))) > IRREGULAR_S:
        # no model, or an event the clock's model leaves that far off: the clock changed
        irregular = model is not None or float(np.ptp(lag)) > IRREGULAR_S
        return ClockOffset(float(np.median(lag)), 0.0, float(t.mean()), float(lag.min()),
                           float(lag.max()), len(lag), False, irregular)  # fmt: skip
    c, rate, t_ref, n = model
    first, last = (c + rate * (log.imu.t[[0, -1]] - t_ref)).tolist()
    least = MIN_OFFSET_S if n > 1 else ONE_EVENT_MIN_S
    # half the rests' events at least: else the fits that agree may be chance (an IMU whose
    # mount is 90 deg off the configured one fitted one event of the sample's four at -5.2 s)
    retime = max(abs(first), abs(last)) >= least and 2 * n >= len(events)
    return ClockOffset(c, rate, t_ref, first, last, n, retime)


def _model(t: Array, lag: Array, weight: Array) -> tuple[float, float, float, int] | None:
    """(offset s at t_ref, rate s/s, t_ref s, events that agree) of the events' lags (s) at
    times t (s), or None: one offset where most events (two or more, or the only one) lie
    within AGREE_S of their median; a steady drift where most (MIN_DRIFT_EVENTS or more,
    over MIN_DRIFT_SPAN_S) lie within AGREE_S of a line through two of them, the line drifts by
    MIN_OFFSET_S or more across them and leaves them under half the offset's rms misfit of all
    the events. Each fitted, and the misfits taken, with the events' weights, over the events
    that agree."""
    inside = np.abs(lag - np.median(lag)) <= AGREE_S
    offset = None
    if len(lag) == 1 or (inside.sum() >= 2 and 2 * inside.sum() >= len(lag)):
        offset = _line(t, lag, weight, inside, drift=False)
    if len(lag) < MIN_DRIFT_EVENTS or np.ptp(t) < MIN_DRIFT_SPAN_S:
        return offset
    best = np.zeros(len(t), dtype=bool)
    for i, j in combinations(range(len(t)), 2):
        if t[j] != t[i]:
            line = lag[i] + (lag[j] - lag[i]) / (t[j] - t[i]) * (t - t[i])
            near = np.abs(lag - line) <= AGREE_S
            best = near if near.sum() > best.sum() else best
    if best.sum() < MIN_DRIFT_EVENTS or 2 * best.sum() < len(lag):
        return offset
    drift = _line(t, lag, weight, best, drift=True)
    if offset is None:
        return drift
    c, _, _, _ = offset
    c2, rate, t_ref, _ = drift
    flat = np.sqrt(np.average((lag - c) ** 2, weights=weight))
    steady = np.sqrt(np.average((lag - c2 - rate * (t - t_ref))[best] ** 2, weights=weight[best]))
    drifted = abs(rate) * float(np.ptp(t[best])) >= MIN_OFFSET_S
    return drift if drifted and steady < 0.5 * flat else offset


def _line(
    t: Array, lag: Array, weight: Array, use: NDArray[np.bool_], drift: bool
) -> tuple[float, float, float, int]:
    """The weighted least-squares offset (and rate, with drift) of the events ``use``."""
    w, tt, ll = weight[use], t[use], lag[use]
    t_ref = float(w @ tt / w.sum())
    rate = float(np.sum(w * (tt - t_ref) * ll) / np.sum(w * (tt - t_ref) ** 2)) if drift else 0.0
    return float(w @ ll / w.sum()), rate, t_ref, int(use.sum())


def taken_out(log: SensorLog, mount: Array) -> tuple[SensorLog, ClockOffset | None]:
    """``log`` as it is to be smoothed (re-timed where its offset is to be taken out) and the
    offset measured in it (:func:`measure`)."""
    offset = measure(log, mount)
    return (retimed(log, offset) if offset is not None and offset.retime else log), offset


def retimed(log: SensorLog, offset: ClockOffset) -> SensorLog:
    """``log`` with the IMU's and the magnetometer's stamps on the odometer's clock."""
    imu = ImuSamples(log.imu.t - offset.at(log.imu.t), log.imu.gyro, log.imu.accel)
    mag = log.mag
    if len(mag.t):
        mag = MagSamples(mag.t - offset.at(mag.t), mag.field)
    return dataclasses.replace(log, imu=imu, mag=mag)


def _events(log: SensorLog) -> list[tuple[float, float, int]]:
    """(rest start, rest end, +1 for the start after it or -1 for the stop before it), the
    longest rests' first."""
    odo = log.odometer
    if len(odo.t) < 2 or len(log.imu.t) < 2:
        return []
    spans = sorted(static_spans(log, REST_MIN_S), key=lambda s: s[0] - s[1])
    events: list[tuple[float, float, int]] = []
    for a, b in spans:
        if b + MOTION_S < odo.t[-1]:
            events.append((a, b, 1))
        if a - MOTION_S > odo.t[0]:
            events.append((a, b, -1))
    return events[:MAX_EVENTS]


def _event(
    log: SensorLog, mount: Array, a: float, b: float, sign: int
) -> tuple[float, float, float, float] | None:
    """(time s, offset s, scale, misfit m rms) of the start after the rest [a, b] (sign +1)
    or the stop before it (-1), or None where it cannot be measured."""
    odo = log.odometer
    edge = b if sign > 0 else a
    lo, hi = (b - 0.5, b + MOTION_S) if sign > 0 else (a - MOTION_S, a + 0.5)
    i, j = np.searchsorted(odo.t, [lo, hi])
    t, d = odo.t[i:j], odo.distance[i:j]
    step = np.flatnonzero(np.diff(d) != 0)
    if len(step) < MIN_CROSSINGS:
        return None
    tc = 0.5 * (t[step] + t[step + 1])  # the count changed between these readings
    dc = d[step + 1] - np.interp(edge, odo.t, odo.distance)
    # the IMU about the event, every lag's rest and motion inside it
    first = (max(a, b - REST_S) if sign > 0 else a - MOTION_S) - SEARCH_S - 1.0
    last = (b + MOTION_S if sign > 0 else min(b, a + REST_S)) + SEARCH_S + 1.0
    k0, k1 = np.searchsorted(log.imu.t, [first, last])
    if k1 - k0 < 2 * MIN_REST_SAMPLES:
        return None
    ti = log.imu.t[k0:k1]
    f = np.asarray(log.imu.accel[k0:k1]) @ mount[0]  # along base_link x
    # each sample is the mean over the interval since the one before (INTERFACES.md)
    ti = np.r_[ti[0], 0.5 * (ti[1:] + ti[:-1])]
    dt = np.diff(ti)
    v = np.r_[0.0, np.cumsum(0.5 * (f[1:] + f[:-1]) * dt)]  # the integrals from ti[0]
    x = np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)]
    imu = (ti, v, x, np.r_[0.0, np.cumsum(f)])
    lags = np.arange(-SEARCH_S, SEARCH_S + STEP_S / 2, STEP_S)
    misfit, scale = _fit(imu, tc, dc, a, b, sign, lags)
    if not np.isfinite(misfit).any():
        return None
    best = lags[int(np.argmin(misfit))]
    lags = best + np.arange(-2 * STEP_S, 2 * STEP_S + FINE_S / 2, FINE_S)
    misfit, scale = _fit(imu, tc, dc, a, b, sign, lags)
    k = int(np.argmin(misfit))
    if not np.isfinite(misfit[k]):
        return None
    return edge, float(lags[k]), float(scale[k]), float(misfit[k])


def _fit(
    imu: tuple[Array, Array, Array, Array],
    tc: Array,
    dc: Array,
    a: float,
    b: float,
    sign: int,
    lags: Array,
) -> tuple[Array, Array]:
    """The rms misfit (m; inf where the lag leaves the data or the scale is out of
    SCALE_RANGE) and the scale of the count's crossings (tc, dc) against the IMU's distance
    from the rest, for each lag of the IMU's stamps. ``imu``: its sample times (s), the first
    and second integrals of its specific force along the axis from its first sample (m/s, m)
    and the running sum of the force (m/s^2), one more element than the samples."""
    t, v, x, total = imu
    if sign > 0:
        r0, r1 = max(a, b - REST_S) + lags, b - MARGIN_S + lags
    else:
        r0, r1 = a + MARGIN_S + lags, min(b, a + REST_S) + lags
    j0, j1 = np.searchsorted(t, r0), np.searchsorted(t, r1)
    n = j1 - j0
    rest = (total[j1] - total[j0]) / np.maximum(n, 1)
    still = r1 if sign > 0 else r0  # the rest's end next to the motion: speed 0 there
    at = tc[None, :] + lags[:, None]
    u = at - still[:, None]
    # distance from the rest: the double integral of (f - rest) from `still`
    dist = (np.interp(at, t, x) - np.interp(still, t, x)[:, None]
            - np.interp(still, t, v)[:, None] * u - rest[:, None] * u**2 / 2)  # fmt: skip
    dd = dist - dist.mean(axis=1, keepdims=True)
    dcc = dc - dc.mean()
    sxx = np.einsum("ij,ij->i", dd, dd)
    scale = np.einsum("ij,j->i", dd, dcc) / np.where(sxx > 0, sxx, np.nan)
    misfit = np.sqrt(np.mean((dcc - scale[:, None] * dd) ** 2, axis=1))
    inside = (n >= MIN_REST_SAMPLES) & (r0 >= t[0]) & (r1 <= t[-1])
    inside &= (at.min(axis=1) >= t[0]) & (at.max(axis=1) <= t[-1])
    sound = (scale > SCALE_RANGE[0]) & (scale < SCALE_RANGE[1])
    return np.where(inside & sound & np.isfinite(misfit), misfit, np.inf), scale
