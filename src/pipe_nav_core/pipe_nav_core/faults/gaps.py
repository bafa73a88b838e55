"""Holes in the time line of a recorded run: clock steps and data gaps.

A stretch where the IMU (and with it every other topic) is silent for much longer than its
sample period is one of two things, told apart by the odometer across it:

- a **clock step**: the logger's clock jumped (a GPS time fix, a reset) while the pig moved on
  as before: the odometer's distance across the hole is what its speed covers in one sample
  period. The stamps after it are moved back by the step, so the run is continuous again, and
  the step is named (its size, where) in the warnings.
- a **data gap**: nothing was recorded while the pig moved (a lost chunk, a logger stall):
  the distance across the hole is what the pig travelled in it. It is named with its length in
  seconds and metres; where the pig moved in it, the run's quality is FAILED (the centreline
  across it is not known: bridging it is not built yet).

All times in s of the bag's header-stamp clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from pipe_nav_core.types import SensorLog

MIN_GAP_S = 1.0  # s: a silence shorter than this (and than 50 IMU periods) is not a hole


@dataclass(frozen=True)
class TimeHole:
    """A silence of the IMU from ``t_before`` to ``t_after`` (s, the samples either side).

    kind: ``clock step``, ``data gap`` or ``rest`` (filled: fill_holes_at_rest); step: s, how
    far the stamps after it were moved back (0 for a data gap); moved: m, odometer distance
    across it.
    """

    t_before: float
    t_after: float
    kind: str
    step: float
    moved: float

    def describe(self) -> str:
        """One line for people."""
        if self.kind == "rest":
            return (
                f"IMU silent for {self.t_after - self.t_before:.1f} s after t = "
                f"{self.t_before:.3f} s while the pig stood still: filled with what it read "
                "either side"
            )
        if self.kind == "clock step":
            return (
                f"clock step of {self.step:+.3f} s after t = {self.t_before:.3f} s (all topics "
                f"silent, the odometer continuous): later stamps moved back by it"
            )
        return (
            f"data gap of {self.t_after - self.t_before:.1f} s after t = {self.t_before:.3f} s "
            f"(the pig moved {self.moved:.2f} m in it)"
        )


def find_holes(log: SensorLog, short: bool = False) -> list[TimeHole]:
    """The clock steps and data gaps of a time-sorted log (see the module); with ``short``,
    every silence over 1.5 IMU periods (after fill_short_holes: the ones it could not fill)."""
    t = log.imu.t
    if len(t) < 3:
        return []
    dt = np.diff(t)
    period = float(np.median(dt))
    limit = 1.5 * period if short else max(MIN_GAP_S, 50.0 * period)
    holes: list[TimeHole] = []
    odo = log.odometer
    odo_period = float(np.median(np.diff(odo.t))) if len(odo.t) > 2 else math.nan
    for i in np.flatnonzero(dt > limit):
        t0, t1 = float(t[i]), float(t[i + 1])
        if len(odo.t) < 2:
            holes.append(TimeHole(t0, t1, "data gap", 0.0, math.nan))
            continue
        j0 = int(np.searchsorted(odo.t, t0, side="right")) - 1
        j1 = int(np.searchsorted(odo.t, t1, side="left"))
        if j0 < 0 or j1 >= len(odo.t):
            holes.append(TimeHole(t0, t1, "data gap", 0.0, math.nan))
            continue
        moved = float(odo.distance[j1] - odo.distance[j0])
        speed = 0.5 * abs(float(odo.speed[j0]) + float(odo.speed[j1]))
        expected = speed * odo_period
        if abs(moved - expected) <= max(0.05, 3.0 * expected) and speed * (t1 - t0) > 1.0:
            holes.append(TimeHole(t0, t1, "clock step", t1 - t0 - period, moved))
        else:
            holes.append(TimeHole(t0, t1, "data gap", 0.0, moved))
    return holes


def remove_clock_steps(log: SensorLog, holes: list[TimeHole]) -> SensorLog:
    """The log with the stamps after each clock step moved back by it (markers included)."""
    steps = [h for h in holes if h.kind == "clock step"]
    if not steps:
        return log

    def fixed(t: np.ndarray) -> np.ndarray:
        out = np.array(t, dtype=np.float64, copy=True)
        for h in steps:
            out = np.where(np.asarray(t) >= h.t_after, out - h.step, out)
        return out

    return retimed(log, fixed)


def retimed(log: SensorLog, f: Callable[[np.ndarray], np.ndarray]) -> SensorLog:
    """The log with every stamp (samples and markers, s) mapped through ``f``."""
    return replace(
        log,
        imu=replace(log.imu, t=f(log.imu.t)),
        odometer=replace(log.odometer, t=f(log.odometer.t)),
        mag=replace(log.mag, t=f(log.mag.t)),
        markers=[replace(m, t=float(f(np.array([m.t]))[0])) for m in log.markers],
    )


def fill_short_holes(log: SensorLog, max_moved: float = 0.5) -> tuple[SensorLog, int, int]:
    """The log with the short IMU holes the filter cannot integrate across (it diverged from
    0.1 s on: dropped samples, left-out shocks) filled at the IMU's rate by interpolating the
    samples either side, where that is safe: the rates and forces either side agree (the
    interpolation then errs by under about a milliradian and 5 cm/s) or the pig moved less
    than ``max_moved`` m in it. The others are left for find_holes (data gaps: segments).
    Returns the log, the holes filled and the samples added."""
    imu = log.imu
    t = imu.t
    if len(t) < 3:
        return log, 0, 0
    dt = np.diff(t)
    period = float(np.median(dt))
    limit = max(MIN_GAP_S, 50.0 * period)
    candidates = np.flatnonzero((dt > 1.5 * period) & (dt <= limit))
    odo = log.odometer
    new_t, filled = [t], 0
    for i in candidates:
        turn = float(np.max(np.abs(imu.gyro[i + 1] - imu.gyro[i]))) * dt[i]
        push = float(np.max(np.abs(imu.accel[i + 1] - imu.accel[i]))) * dt[i]
        moved = (float(np.ptp(np.interp([t[i], t[i + 1]], odo.t, odo.distance)))
                 if len(odo.t) > 1 else 0.0)  # fmt: skip
        if (turn > 1e-3 or push > 0.05) and moved > max_moved:
            continue
        n = int(round(dt[i] / period)) - 1
        if n > 0:
            new_t.append(t[i] + dt[i] * np.arange(1, n + 1) / (n + 1))
            filled += 1
    if filled == 0:
        return log, 0, 0
    tt = np.sort(np.concatenate(new_t), kind="stable")

    def fill(x: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(tt, t, x[:, c]) for c in range(x.shape[1])], axis=1)

    added = len(tt) - len(t)
    return (
        replace(log, imu=replace(imu, t=tt, gyro=fill(imu.gyro), accel=fill(imu.accel))),
        filled,
        added,
    )


REST_WINDOW_S = 0.5  # s of IMU samples either side of a hole at rest averaged for its filling
REST_MOVED_M = 0.01  # m: the odometer moved less than this across a hole at rest ...
REST_SPEED = 0.01  # m/s: ... and read less than this speed at either end
REST_TILT = 2e-3  # rad: the gravity direction either side agrees to this (the pig did not roll)
REST_RATE = 2e-3  # rad/s: and the mean rates to this


def same_at_rest(
    gyro0: ArrayLike, accel0: ArrayLike, gyro1: ArrayLike, accel1: ArrayLike, slack: float = 1.0
) -> bool:
    """Whether IMU readings before (gyro0 rad/s, accel0 m/s^2) and after a hole agree as a pig
    standing still reads them: the gravity direction within REST_TILT and every rate within
    REST_RATE, both times ``slack`` (for single samples rather than window means)."""
    a0, a1 = np.asarray(accel0, dtype=np.float64), np.asarray(accel1, dtype=np.float64)
    cos = float(a0 @ a1 / max(np.linalg.norm(a0) * np.linalg.norm(a1), 1e-12))
    rates = float(np.max(np.abs(np.subtract(gyro1, gyro0))))
    return math.acos(min(1.0, cos)) <= slack * REST_TILT and rates <= slack * REST_RATE


def fill_holes_at_rest(log: SensorLog) -> tuple[SensorLog, list[TimeHole]]:
    """The log with the IMU holes longer than fill_short_holes takes, but while the pig stood
    still (a logger stall, a shock left out, at a stop), filled at the IMU's rate with the mean
    of the REST_WINDOW_S either side, linearly from one to the other: standing still, the IMU
    reads the same before and after, so the filled samples are what it would have read. At
    rest means: the odometer moved under REST_MOVED_M across the hole, its speed either side
    is under REST_SPEED, and the gravity direction and the mean rate either side agree
    (REST_TILT, REST_RATE: the pig did not roll over in it). Returns the log and the holes
    filled (kind ``rest``)."""
    imu, odo = log.imu, log.odometer
    t = imu.t
    if len(t) < 3 or len(odo.t) < 2:
        return log, []
    dt = np.diff(t)
    period = float(np.median(dt))
    limit = max(MIN_GAP_S, 50.0 * period)
    filled: list[TimeHole] = []
    parts_t, parts_g, parts_a = [t], [imu.gyro], [imu.accel]
    for i in np.flatnonzero(dt > limit):
        t0, t1 = float(t[i]), float(t[i + 1])
        d0, d1 = np.interp([t0, t1], odo.t, odo.distance)
        j0 = max(int(np.searchsorted(odo.t, t0, side="right")) - 1, 0)
        j1 = min(int(np.searchsorted(odo.t, t1, side="left")), len(odo.t) - 1)
        if (
            abs(d1 - d0) >= REST_MOVED_M
            or max(abs(odo.speed[j0]), abs(odo.speed[j1])) >= REST_SPEED
        ):
            continue
        before = (t > t0 - REST_WINDOW_S) & (t <= t0)
        after = (t >= t1) & (t < t1 + REST_WINDOW_S)
        if before.sum() < 3 or after.sum() < 3:
            continue
        g0, g1 = imu.gyro[before].mean(axis=0), imu.gyro[after].mean(axis=0)
        a0, a1 = imu.accel[before].mean(axis=0), imu.accel[after].mean(axis=0)
        if not same_at_rest(g0, a0, g1, a1):
            continue
        n = int(round((t1 - t0) / period)) - 1
        if n <= 0:
            continue
        f = (np.arange(1, n + 1) / (n + 1))[:, None]
        parts_t.append(t0 + (t1 - t0) * f[:, 0])
        parts_g.append(g0 + f * (g1 - g0))
        parts_a.append(a0 + f * (a1 - a0))
        filled.append(TimeHole(t0, t1, "rest", 0.0, float(d1 - d0)))
    if not filled:
        return log, []
    tt = np.concatenate(parts_t)
    order = np.argsort(tt, kind="stable")
    imu = replace(imu, t=tt[order], gyro=np.concatenate(parts_g)[order],
                  accel=np.concatenate(parts_a)[order])  # fmt: skip
    return replace(log, imu=imu), filled
