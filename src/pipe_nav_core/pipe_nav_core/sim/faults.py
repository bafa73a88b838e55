"""Field faults injected into a recorded log, for the fault corpus of the tests and the bench.

Each injector takes a SensorLog and returns a damaged copy (the input is not modified); ``at``
and ``dur`` are seconds from the log's first IMU sample. :data:`CORPUS` names one case per
fault of issue 16 with the words the tools must use for it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from pipe_nav_core.faults.gaps import retimed
from pipe_nav_core.geo.earth import enu_to_geodetic
from pipe_nav_core.smooth.segments import samples_where
from pipe_nav_core.types import SensorLog


def _t0(log: SensorLog) -> float:
    return float(log.imu.t[0])


def clock_step(log: SensorLog, at: float, step: float) -> SensorLog:
    """The logger's clock jumps by ``step`` s at ``at``."""
    t_at = _t0(log) + at
    return retimed(log, lambda t: np.where(t > t_at, t + step, t))


def data_gap(log: SensorLog, at: float, dur: float) -> SensorLog:
    """Nothing recorded on any topic from ``at`` for ``dur`` s (markers kept)."""
    a, b = _t0(log) + at, _t0(log) + at + dur
    return samples_where(log, lambda t: (t < a) | (t > b))


def imu_dropped(log: SensorLog, at: float, dur: float) -> SensorLog:
    """IMU samples lost from ``at`` for ``dur`` s (the other topics go on)."""
    t = log.imu.t
    return replace(log, imu=log.imu.slice(~((t > _t0(log) + at) & (t < _t0(log) + at + dur))))


def imu_shock(log: SensorLog, at: float, dur: float, seed: int = 1) -> SensorLog:
    """``dur`` s of violent readings clipped at a +-16 g, +-2000 deg/s sensor's range."""
    rng = np.random.default_rng(seed)
    imu = log.imu
    k = (imu.t > _t0(log) + at) & (imu.t < _t0(log) + at + dur)
    g, a = imu.gyro.copy(), imu.accel.copy()
    g[k] = np.clip(rng.normal(0.0, 30.0, (int(k.sum()), 3)), -34.9, 34.9)
    a[k] = np.clip(rng.normal(0.0, 120.0, (int(k.sum()), 3)), -156.9, 156.9)
    return replace(log, imu=replace(imu, gyro=g, accel=a))


def imu_pinned(log: SensorLog, at: float, dur: float, value: float = 78.4) -> SensorLog:
    """The x accelerometer pinned at ``value`` m/s^2 (an 8 g range limit) for ``dur`` s."""
    imu = log.imu
    a = imu.accel.copy()
    a[(imu.t > _t0(log) + at) & (imu.t < _t0(log) + at + dur), 0] = value
    return replace(log, imu=replace(imu, accel=a))


def odometer_stuck(log: SensorLog, at: float, dur: float) -> SensorLog:
    """The wheel stands still from ``at`` for ``dur`` s, then counts on from there."""
    o = log.odometer
    k = (o.t > _t0(log) + at) & (o.t < _t0(log) + at + dur)
    i0, i1 = np.flatnonzero(k)[[0, -1]]
    d, v = o.distance.copy(), o.speed.copy()
    d[k], v[k] = d[i0], 0.0
    d[o.t >= _t0(log) + at + dur] -= o.distance[i1] - o.distance[i0]
    return replace(log, odometer=replace(o, distance=d, speed=v))


def odometer_spike(log: SensorLog, at: float, size: float, step: bool = False) -> SensorLog:
    """One reading ``size`` m off at ``at`` (``step``: that reading and all after it)."""
    o = log.odometer
    d = o.distance.copy()
    j = int(np.searchsorted(o.t, _t0(log) + at))
    if step:
        d[j:] += size
    else:
        d[j] += size
    return replace(log, odometer=replace(o, distance=d))


def imu_clock(log: SensorLog, offset: float, ppm: float = 0.0) -> SensorLog:
    """The IMU (and its magnetometer) stamped on a clock of its own: ``offset`` s late at the
    first IMU sample, running ``ppm`` parts per million fast from there."""
    t0 = _t0(log)

    def late(t: np.ndarray) -> np.ndarray:
        return t + offset + 1e-6 * ppm * (t - t0)

    imu = replace(log.imu, t=late(log.imu.t))
    return replace(log, imu=imu, mag=replace(log.mag, t=late(log.mag.t)))


def mag_clock(log: SensorLog, offset: float) -> SensorLog:
    """The magnetometer alone stamped ``offset`` s late (a board of its own)."""
    return replace(log, mag=replace(log.mag, t=log.mag.t + offset))


def markers_clock(log: SensorLog, offset: float) -> SensorLog:
    """Every marker's passage stamped ``offset`` s late (a marker file on another clock: GPS
    time is 18 s ahead of UTC)."""
    return replace(log, markers=[replace(m, t=m.t + offset) for m in log.markers])


def marker_moved(log: SensorLog, index: int, east: float, north: float = 0.0) -> SensorLog:
    """Marker ``index`` (in time order) surveyed ``east``/``north`` m off."""
    markers = sorted(log.markers, key=lambda m: m.t)
    m = markers[index]
    lat, lon, _ = enu_to_geodetic(np.array([east, north, 0.0]), m.lat, m.lon, m.alt)
    markers[index] = replace(m, lat=float(lat), lon=float(lon))
    return replace(log, markers=markers)


def marker_late(log: SensorLog, index: int, late: float) -> SensorLog:
    """Marker ``index`` (in time order) stamped ``late`` s after its passage."""
    markers = sorted(log.markers, key=lambda m: m.t)
    markers[index] = replace(markers[index], t=markers[index].t + late)
    return replace(log, markers=markers)


@dataclass(frozen=True)
class FaultCase:
    """One fault: its name, the injector (log, run duration s -> damaged log) and the words
    the warnings must contain."""

    name: str
    inject: Callable[[SensorLog, float], SensorLog]
    named: str


CORPUS = (
    FaultCase("marker surveyed 20 m off", lambda lg, d: marker_moved(lg, 2, 20.0), "left out"),
    FaultCase("marker stamped 3 s late", lambda lg, d: marker_late(lg, 2, 3.0), "left out"),
    FaultCase(
        "markers on GPS time (18 s late)", lambda lg, d: markers_clock(lg, 18.0), "marker clock"
    ),  # fmt: skip
    FaultCase("data gap of 30 s", lambda lg, d: data_gap(lg, 0.42 * d, 30.0), "data gap"),
    FaultCase(
        "clock step of an hour", lambda lg, d: clock_step(lg, 0.5 * d, 3600.0), "clock step"
    ),  # fmt: skip
    FaultCase("IMU shock of 5 s", lambda lg, d: imu_shock(lg, 0.53 * d, 5.0), "IMU shock"),
    FaultCase(
        "IMU pinned at 8 g for 0.2 s", lambda lg, d: imu_pinned(lg, 0.3 * d, 0.2), "IMU saturated"
    ),  # fmt: skip
    FaultCase(
        "IMU samples dropped for 0.3 s", lambda lg, d: imu_dropped(lg, 0.53 * d, 0.3), "IMU"
    ),  # fmt: skip
    FaultCase("IMU clock 0.3 s late", lambda lg, d: imu_clock(lg, 0.3), "IMU clock"),
    FaultCase(
        "magnetometer clock 0.3 s late", lambda lg, d: mag_clock(lg, 0.3), "magnetometer clock"
    ),  # fmt: skip
    FaultCase(
        "wheel stuck for 20 s", lambda lg, d: odometer_stuck(lg, 0.21 * d, 20.0), "odometer stuck"
    ),  # fmt: skip
    FaultCase(
        "odometer spike of 5 m", lambda lg, d: odometer_spike(lg, 0.53 * d, 5.0), "odometer spike"
    ),  # fmt: skip
    FaultCase(
        "odometer step of -0.5 m",
        lambda lg, d: odometer_spike(lg, 0.53 * d, -0.5, True),
        "backward step",
    ),  # fmt: skip
)
