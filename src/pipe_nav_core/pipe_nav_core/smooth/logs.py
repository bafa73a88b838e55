"""Cutting and turning sensor logs for the smoothing passes: a time slice, the log up to a
time, and the log in reversed time (for the backward filter and runs aligned at their end);
and a log's IMU samples read from a file, in memory only while they are read (:func:`map_imu`)."""

from __future__ import annotations

import math
import mmap

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.memory import Spool, mapping, root
from pipe_nav_core.types import (
    ImuSamples,
    MagSamples,
    Marker,
    OdometerSamples,
    SensorLog,
    markers_sorted,
)

MAP_IMU_BYTES = 256 << 20  # IMU samples larger than this are read from a file (map_imu)


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


def map_imu(imu: ImuSamples) -> None:
    """Put the samples of ``imu`` in a file and read them from there, mapped read-only (in
    place; the same values): then only what is read is in memory, and what has been read can
    be let go (:func:`let_go`). At 100 km the IMU is 0.58 GB that the RTS smoother, the
    centreline and most products never read, and that a filter pass reads once, in order.
    Nothing is done when the samples are under MAP_IMU_BYTES, already mapped, or not the whole
    of their memory (a slice keeps its base in memory anyway), or when the temporary folder
    has no room for them. The file's name is removed at once: its space goes with the
    mapping."""
    arrays = (imu.t, imu.gyro, imu.accel)
    if not len(imu) or sum(a.nbytes for a in arrays) < MAP_IMU_BYTES:
        return
    if any(mapping(a) is not None for a in arrays) or not all(map(_whole, arrays)):
        return
    mapped = []
    for a in arrays:
        spool = Spool(a.shape[1:])
        spool.append(a)
        if not spool.in_file:  # no room for the file (a full or read-only temporary folder)
            return
        mapped.append(spool.gathered())
    if all(mapping(m) is not None for m in mapped):  # else one could not be mapped: in memory
        imu.t, imu.gyro, imu.accel = mapped


def let_go(imu: ImuSamples, before: float = math.inf) -> None:
    """Give back the memory of the mapped samples (:func:`map_imu`) stamped before ``before``
    (s; all by default): read again, they come back from the file."""
    arrays = (imu.t, imu.gyro, imu.accel)
    maps = [mapping(a) for a in arrays]
    if any(m is None for m in maps):
        return
    rows = len(imu) if before == math.inf else int(np.searchsorted(imu.t, before))
    for a, m in zip(arrays, maps):
        size = rows * a.strides[0]
        size -= size % mmap.PAGESIZE
        if size > 0 and m is not None:
            m.madvise(mmap.MADV_DONTNEED, 0, size)


def _whole(a: NDArray[np.float64]) -> bool:
    """Whether a is contiguous and all of the memory it views (its own, or a reshape's)."""
    return a.flags.c_contiguous and root(a).nbytes == a.nbytes
