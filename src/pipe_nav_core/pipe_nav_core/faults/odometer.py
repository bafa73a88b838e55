"""Wheel odometer faults the IMU can vouch against: a stuck wheel, spikes and steps.

The pig's speed cannot change faster than a few m/s^2 without a shock the IMU would feel. A
change of the odometer's speed (its distance differenced over ``WINDOW_S`` before and after
each reading) beyond ``A_MAX`` x the window, with no matching jolt in the specific force, is a
fault of the wheel, not motion. Between the breaks:

- **stuck**: the distance stands still for ``MIN_STUCK_S`` or more after the wheel stopped
  faster than ``A_STOP`` with no jolt: the readings until it turns again are left out (else
  they read as a stop and the filter's zero-velocity updates hold the pig back);
- **spike**: the distance jumps and comes back within a window: those readings are left out;
- **step**: the distance jumps by some metres (or back) in one reading and goes on from there:
  named; the filter's gate rejects the one increment, and the chainage (distance_m) comes
  from the smoothed path, not from the count.

Slips (the wheel reading slow or fast, or standing still for under ``MIN_STUCK_S``, over a
few readings) are not faults here: pigs slip often, and the smoother finds and leaves out
those epochs itself (smooth.slips.find_slips).

Times s of the header-stamp clock, distances m.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pipe_nav_core.types import SensorLog

WINDOW_S = 0.25  # s, the speed is differenced over this before and after each reading
A_MAX = 3.0  # m/s^2, faster speed changes need a shock in the IMU
MIN_MOVING = 0.1  # m/s, a wheel standing still is stuck only if the pig moved around it
MIN_STUCK_S = 2.0  # s: a wheel standing still for less is a slip (the smoother handles those)
A_STOP = 1.0  # m/s^2: a wheel that stops faster than this, with no jolt, is stuck


@dataclass(frozen=True)
class OdometerFault:
    """kind: ``stuck``, ``spike`` or ``step``; from t0 to t1 (s); size: m (the distance the
    stuck wheel missed, the spike's height, the step); dropped: readings left out."""

    kind: str
    t0: float
    t1: float
    size: float
    dropped: int

    def describe(self) -> str:
        if self.kind == "stuck":
            return (
                f"odometer stuck for {self.t1 - self.t0:.1f} s from t = {self.t0:.3f} s (it "
                f"stopped dead with no jolt in the IMU; up to {self.size:.1f} m unread): its "
                f"{self.dropped} readings left out"
            )
        if self.kind == "spike":
            return (
                f"odometer spike of {self.size:+.2f} m at t = {self.t0:.3f} s: "
                f"{self.dropped} reading(s) left out"
            )
        way = "backward " if self.size < 0 else ""
        return f"odometer {way}step of {self.size:+.2f} m at t = {self.t0:.3f} s (not motion)"


def _speeds(t: np.ndarray, d: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Speed over the n readings before and after each one (m/s; nan near the ends)."""
    vb = np.full(len(t), np.nan)
    va = np.full(len(t), np.nan)
    vb[n:] = (d[n:] - d[:-n]) / (t[n:] - t[:-n])
    va[:-n] = (d[n:] - d[:-n]) / (t[n:] - t[:-n])
    return vb, va


def _jolt(log: SensorLog, t0: float, t1: float) -> float:
    """Largest deviation (m/s^2) of |specific force| from its median around [t0, t1]."""
    t = log.imu.t  # time-sorted: each window is an index range, not a pass over the run

    def samples(pad: float) -> tuple[int, int]:
        return int(np.searchsorted(t, t0 - pad, "left")), int(np.searchsorted(t, t1 + pad, "right"))

    (i, j), (a, b) = samples(WINDOW_S), samples(10 * WINDOW_S)
    if i >= j or a >= b:
        return np.inf  # no IMU to vouch against the wheel: trust it
    norm = np.linalg.norm(log.imu.accel[a:b], axis=1)
    return float(np.max(np.abs(norm[i - a : j - a] - np.median(norm))))


def find_odometer_faults(log: SensorLog, resolution: float = 0.0) -> list[OdometerFault]:
    """The faults of a time-sorted log's odometer (see the module); resolution: m per count
    (0: the smallest step in the readings)."""
    odo = log.odometer
    t, d = odo.t, odo.distance
    if len(t) < 8:
        return []
    period = float(np.median(np.diff(t)))
    n = max(int(round(WINDOW_S / period)), 2)
    steps = np.abs(np.diff(d))
    res = resolution or (float(np.min(steps[steps > 0])) if (steps > 0).any() else 0.0)
    vb, va = _speeds(t, d, n)
    w = n * period
    faults = _stuck(log, t, d, vb, n, w, res)
    inside = [(f.t0, f.t1) for f in faults]
    limit = A_MAX * 2 * w + 4 * res / w
    breaks = [i for i in np.flatnonzero(np.abs(va - vb) > limit)
              if not any(a - 2 * w <= t[i] <= b + 2 * w for a, b in inside)]  # fmt: skip
    events: list[tuple[int, int]] = []  # index ranges of readings around one break
    for i in breaks:
        if events and i - events[-1][1] <= n:
            events[-1] = (events[-1][0], int(i))
        else:
            events.append((int(i), int(i)))
    for a, b in events:
        dv = float(np.nan_to_num(va[a] - vb[a]))
        if _jolt(log, t[a], t[b]) > 0.3 * abs(dv) / (2 * w):
            continue  # the IMU felt it: real motion
        lo, hi = max(a - n, 0), min(b + n, len(t) - 1)
        trend_before = d[lo] + (vb[a] if np.isfinite(vb[a]) else 0.0) * (t[hi] - t[lo])
        offset = float(d[hi] - trend_before)
        height = float(np.max(np.abs(d[a : b + 1] - np.interp(t[a : b + 1], t[[lo, hi]],
                                                              d[[lo, hi]]))))  # fmt: skip
        inc = np.diff(d[lo : hi + 1])
        jump = float(np.max(np.abs(inc - np.median(inc))))  # one reading's jump, not a slip
        if abs(offset) <= max(2 * res, 0.5 * height):
            faults.append(OdometerFault("spike", float(t[a]), float(t[b]), height, 0))
        elif jump >= 0.8 * abs(offset):
            faults.append(OdometerFault("step", float(t[a]), float(t[b]), offset, 0))
    return sorted(faults, key=lambda f: f.t0)


def _stuck(
    log: SensorLog, t: np.ndarray, d: np.ndarray, vb: np.ndarray, n: int, w: float, res: float
) -> list[OdometerFault]:
    """Stretches of at least MIN_STUCK_S where the wheel stands still, entered faster than
    A_STOP decelerates (the speed over the window before, over one window) with no jolt in
    the IMU: stuck until the wheel turns again."""
    still = np.r_[False, np.abs(np.diff(d)) <= 0.0]
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(np.int8), 0]))
    out = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        start, end = a - 1, min(b, len(t) - 1)  # the last reading before, the first that moved
        if start < n or t[end] - t[start] < MIN_STUCK_S or not np.isfinite(vb[start]):
            continue
        # the median step over the window before (a one-reading jump into a stop is a step,
        # not the speed the wheel stopped from)
        inc = np.diff(d[start - n : start + 1])
        before = abs(float(np.median(inc) / np.median(np.diff(t[start - n : start + 1]))))
        if before < MIN_MOVING or before / w < A_STOP:
            continue  # a gradual stop: the pig stopped
        if _jolt(log, t[start], t[start + 1]) > 0.3 * before / w:
            continue  # the IMU felt a stop that sudden: it happened
        missed = before * float(t[end] - t[start])  # if it kept its speed
        # from the reading before: the one it stopped at may carry the stuck speed already
        out.append(OdometerFault("stuck", float(t[start - 1]), float(t[end]), missed, 0))
    return out


def without_faults(
    log: SensorLog, faults: list[OdometerFault]
) -> tuple[SensorLog, list[OdometerFault]]:
    """The log without the readings of stuck and spike faults, and the faults with the number
    of readings left out."""
    odo = log.odometer
    keep = np.ones(len(odo.t), bool)
    out: list[OdometerFault] = []
    for f in faults:
        if f.kind == "stuck":
            k = (odo.t > f.t0) & (odo.t < f.t1)
        elif f.kind == "spike":
            k = _spike_readings(odo.t, odo.distance, f)
        else:
            out.append(f)
            continue
        keep &= ~k
        out.append(replace(f, dropped=int(k.sum())))
    if keep.all():
        return log, out
    return replace(log, odometer=replace(odo, t=odo.t[keep], distance=odo.distance[keep],
                                         speed=odo.speed[keep])), out  # fmt: skip


def _spike_readings(t: np.ndarray, d: np.ndarray, f: OdometerFault) -> np.ndarray:
    """The readings of a spike: those in its event off the line through its neighbours."""
    k = np.flatnonzero((t >= f.t0 - WINDOW_S) & (t <= f.t1 + WINDOW_S))
    if len(k) < 3:
        return np.zeros(len(t), bool)
    line = np.interp(t[k], t[k[[0, -1]]], d[k[[0, -1]]])
    off = np.abs(d[k] - line) > 0.5 * abs(f.size)
    out = np.zeros(len(t), bool)
    out[k[off]] = True
    return out


BRIDGE_MIN_S = 1.0  # s: odometer silences longer than this are bridged for dead reckoning


def bridged_for_dead_reckoning(log: SensorLog) -> SensorLog:
    """The log with each odometer silence over BRIDGE_MIN_S (the readings of a stuck wheel left
    out) filled at the mean of the speeds either side, and the readings after it moved on by
    what that speed covers, as if the wheel had kept turning. Only for the dead reckoning that
    finds the initial heading (smooth.heading.anchored_config), where the distance is the only
    motion there is: an error of the assumed speed lengthens the path, it barely turns the
    bearing the heading is anchored on. The filter itself keeps the IMU across the hole."""
    odo = log.odometer
    if len(odo.t) < 3:
        return log
    dt = np.diff(odo.t)
    period = float(np.median(dt))
    holes = np.flatnonzero(dt > max(BRIDGE_MIN_S, 5.0 * period))
    if not len(holes):
        return log
    t, d, v = [odo.t], [odo.distance.copy()], [odo.speed]
    shift = np.zeros(len(odo.t))
    for i in holes:
        t0, t1 = float(odo.t[i]), float(odo.t[i + 1])
        speed = 0.5 * (float(odo.speed[i]) + float(odo.speed[i + 1]))
        n = int(round((t1 - t0) / period)) - 1
        tt = t0 + (t1 - t0) * np.arange(1, n + 1) / (n + 1)
        t.append(tt)
        d.append(odo.distance[i] + shift[i] + speed * (tt - t0))
        v.append(np.full(n, speed))
        shift[i + 1 :] += odo.distance[i] + speed * (t1 - t0) - odo.distance[i + 1]
    d[0] = d[0] + shift  # (each hole's fill started from its reading already shifted)
    tt, dd, vv = (np.concatenate(x) for x in (t, d, v))
    order = np.argsort(tt, kind="stable")
    return replace(log, odometer=replace(odo, t=tt[order], distance=dd[order], speed=vv[order]))
