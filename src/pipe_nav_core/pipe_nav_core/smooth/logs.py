"""Cutting and turning sensor logs for the smoothing passes: a time slice, the log up to a
time, and the log in reversed time (for the backward filter and runs aligned at their end)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.types import (
    ImuSamples,
    MagSamples,
    Marker,
    OdometerSamples,
    SensorLog,
    markers_sorted,
)


def slice_log(log: SensorLog, t0: float, t1: float) -> SensorLog:
    """The samples and markers of a time-sorted log with stamps in [t0, t1), s."""

    def sel(t: NDArray[np.float64]) -> slice:
        return slice(int(np.searchsorted(t, t0, "left")), int(np.searchsorted(t, t1, "left")))

    return SensorLog(
        log.imu.slice(sel(log.imu.t)),
        log.odometer.slice(sel(log.odometer.t)),
        log.mag.slice(sel(log.mag.t)),
        [m for m in log.markers if t0 <= m.t < t1],
    )


def log_until(log: SensorLog, t_end: float) -> SensorLog:
    """The samples and markers of a time-sorted log stamped at or before t_end, s."""
    return slice_log(log, -math.inf, math.nextafter(t_end, math.inf))


def reverse_log(log: SensorLog) -> SensorLog:
    """The log in reversed time (t -> -t): IMU sample i (the mean over (t[i-1], t[i]]) becomes
    a sample stamped -t[i-1] with negated rate; odometer speed negated; markers re-stamped."""
    imu = log.imu
    t = -imu.t[:-1][::-1]
    rimu = ImuSamples(t, -imu.gyro[1:][::-1], imu.accel[1:][::-1])
    o = log.odometer
    rodo = OdometerSamples(-o.t[::-1], o.distance[::-1], -o.speed[::-1])
    m = log.mag
    rmag = MagSamples(-m.t[::-1], m.field[::-1])
    markers = [
        Marker(k.name, -k.t, k.lat, k.lon, k.alt, k.sigma_enu)
        for k in markers_sorted(log.markers)[::-1]
    ]
    return SensorLog(rimu, rodo, rmag, markers)
