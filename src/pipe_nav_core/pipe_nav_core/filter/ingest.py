"""The samples of one filter pass, from their arrival to the epoch that uses them.

Pushed samples are checked (a NaN or infinite value: counted and dropped), held in the reorder
window (:class:`~pipe_nav_core.filter.stream.ReorderBuffer`) and released in stamp order into the
buffers the epochs read: IMU rates (rad/s) and specific forces (m/s^2) and magnetometer fields
(T, hard iron removed) rotated from imu_link into base_link, odometer readings, pending
marker passages. The buffers are views trimmed as the epochs consume them.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.stream import Released, ReorderBuffer
from pipe_nav_core.types import MagSamples, Marker, OdometerSamples, SensorLog

Array = NDArray[np.float64]

RELEASE_EVERY_S = 0.05  # s of stamp time between releases (the results do not depend on it) ...
RELEASE_HELD = 4096  # ... unless the reorder window holds this many samples
MAG_KEEP_S = 1.0  # s: magnetometer samples kept before the state's time
# s: an epoch is a stop only if the odometer stands still this long before and after it too. A
# count is blind below one step: a pig starting at 0.3 m/s^2 moves 0.26 s and 0.08 m/s before a
# 1 cm encoder counts, and stops as long after its last count; a zero-velocity update there
# tells the filter a speed that is not zero (it biased the pitch rate's scale factor 0.2-0.5 %).
# An epoch still so far waits for the readings after it (filter.planner.plan): live, a stop's
# estimates come this much later, a moving pig's no later
STOP_MARGIN_S = 0.5


def mount_rotation(rpy: Sequence[float]) -> Array:
    """Rotation imu_link -> base_link from (roll, pitch, yaw) rad: Rz(yaw) Ry(pitch) Rx(roll)."""
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def apply_mount(log: SensorLog, config: NavConfig) -> SensorLog:
    """The log with imu_link vectors rotated into base_link per config.imu_mount_rpy."""
    return log.to_base_link(mount_rotation(config.imu_mount_rpy))


class Inbox:
    """The reorder window and the sample buffers of one pass. counts: the navigator's
    counters (received and dropped samples are counted here); first: the first marker when
    the survey gives it (else the first one passed, when it comes)."""

    def __init__(
        self, config: NavConfig, counts: defaultdict[str, int], first: Marker | None
    ) -> None:
        self.reorder = ReorderBuffer(config.reorder_window_s)
        self.r_base_imu = mount_rotation(config.imu_mount_rpy)
        self.hard_iron = np.asarray(config.mag_hard_iron, dtype=np.float64)
        self.imu_t = np.empty(0)  # s
        self.imu_g = np.empty((0, 3))  # rad/s, base_link
        self.imu_a = np.empty((0, 3))  # m/s^2, base_link
        self.odo = OdometerSamples(np.empty(0), np.empty(0), np.empty(0))
        self.mag = MagSamples(np.empty(0), np.empty((0, 3)))
        self.markers: list[Marker] = []  # passages not yet processed, in time order
        self.markers_seen: list[Marker] = []  # every passage received
        self.first_marker = first
        self.horizon = -math.inf  # s: stamp time up to which all data are in
        self._counts = counts
        self._received = {k: f"received_{k}" for k in ("imu", "odometer", "mag", "marker")}
        self._next_release = -math.inf  # s: a sample stamped from then on releases

    # ------------------------------------------------------------------ one sample at a time
    def imu_sample(self, t: float, gyro: Sequence[float], accel: Sequence[float]) -> object:
        """The payload of an IMU sample: (rate x, y, z rad/s, specific force x, y, z m/s^2),
        imu_link; None (counted) if not finite."""
        gx, gy, gz = (float(v) for v in gyro)  # scalars: numpy per sample costs more here
        ax, ay, az = (float(v) for v in accel)
        if not all(map(math.isfinite, (t, gx, gy, gz, ax, ay, az))):
            self._counts["dropped_nan_imu"] += 1
            return None
        return (gx, gy, gz, ax, ay, az)

    def odometer_sample(self, t: float, distance: float, speed: float) -> object:
        """The payload of an odometer sample (m, m/s), None (counted) if not finite."""
        if not all(math.isfinite(x) for x in (t, distance, speed)):
            self._counts["dropped_nan_odometer"] += 1
            return None
        return (float(distance), float(speed))

    def mag_sample(self, t: float, field_t: Sequence[float]) -> object:
        """The payload of a magnetometer sample (T, imu_link), None (counted) if not finite."""
        m = np.asarray(field_t, dtype=np.float64).reshape(3)
        if not (math.isfinite(t) and np.all(np.isfinite(m))):
            self._counts["dropped_nan_mag"] += 1
            return None
        return m

    def marker_sample(self, marker: Marker) -> object:
        """The marker, None (counted) if a value of it is not finite."""
        vals = (marker.t, marker.lat, marker.lon, marker.alt, *marker.sigma_enu)
        if not all(math.isfinite(x) for x in vals):
            self._counts["dropped_nan_marker"] += 1
            return None
        return marker

    def push(self, t: float, kind: str, payload: object) -> bool:
        """A checked sample into the reorder window; True when samples left it for the
        buffers. Samples are released when the stamps have moved on RELEASE_EVERY_S since the
        last release (a few times per filter epoch, whatever the sensor rates; the results do
        not depend on it), or when the window holds RELEASE_HELD samples."""
        self._counts[self._received[kind]] += 1
        self.reorder.push(t, kind, payload)
        if t < self._next_release and len(self.reorder) < RELEASE_HELD:
            return False
        self._next_release = t + RELEASE_EVERY_S
        released = self.reorder.release()
        if released:
            self._take(released, self.reorder.horizon)
        return bool(released)

    def flush(self) -> None:
        """End of data: everything in the reorder window into the buffers."""
        self._take(self.reorder.release(flush=True), math.inf)

    def _take(self, released: Released, horizon: float) -> None:
        none: tuple[list[float], list[object]] = ([], [])
        imu_t, imu = released.get("imu", none)
        odo_t, odo = released.get("odometer", none)
        mag_t, mag = released.get("mag", none)
        ga = np.array(imu, dtype=np.float64).reshape(-1, 6)
        o = np.array(odo, dtype=np.float64).reshape(-1, 2)
        self.add(
            np.array(imu_t, dtype=np.float64), ga[:, :3], ga[:, 3:],
            OdometerSamples(np.array(odo_t, dtype=np.float64), o[:, 0], o[:, 1]),
            MagSamples(np.array(mag_t, dtype=np.float64),
                       np.array(mag, dtype=np.float64).reshape(-1, 3)),
            released.get("marker", none)[1],  # type: ignore[arg-type]
            horizon,
        )  # fmt: skip

    # ------------------------------------------------------------------ a log at a time
    def add_log(self, log: SensorLog, final: bool) -> None:
        """A time-sorted log (imu_link), or one of consecutive chunks of one (final: the
        last), straight into the buffers; non-finite IMU samples are counted and dropped."""
        imu = log.imu
        t, gyro, accel = imu.t, imu.gyro, imu.accel
        dropped = 0
        # the whole chunk checked at once (a log's samples are finite but where a fault is):
        # per-sample masks and the copies they index cost a tenth of a filter pass
        if not (np.isfinite(t).all() and np.isfinite(gyro).all() and np.isfinite(accel).all()):
            ok = np.isfinite(t) & np.all(np.isfinite(gyro), 1) & np.all(np.isfinite(accel), 1)
            dropped = int((~ok).sum())
            t, gyro, accel = t[ok], gyro[ok], accel[ok]
        self._counts["dropped_nan_imu"] += dropped
        horizon = math.inf if final else _last_stamp(log)
        self.add(t, gyro, accel, log.odometer, log.mag, list(log.markers), horizon)

    def add(
        self,
        imu_t: Array,
        gyro: Array,
        accel: Array,
        odo: OdometerSamples,
        mag: MagSamples,
        markers: list[Marker],
        horizon: float,
    ) -> None:
        """Time-sorted samples (imu_link) into the buffers; horizon: s, the stamp time up to
        which all data are now in."""
        r = self.r_base_imu
        if len(imu_t):
            self.imu_t = np.concatenate([self.imu_t, imu_t])
            self.imu_g = np.concatenate([self.imu_g, gyro @ r.T])
            self.imu_a = np.concatenate([self.imu_a, accel @ r.T])
        if len(odo):
            self.odo = OdometerSamples(
                np.concatenate([self.odo.t, odo.t]),
                np.concatenate([self.odo.distance, odo.distance]),
                np.concatenate([self.odo.speed, odo.speed]),
            )
        if len(mag):
            self.mag = MagSamples(
                np.concatenate([self.mag.t, mag.t]),
                np.concatenate([self.mag.field, (mag.field - self.hard_iron) @ r.T]),
            )
        for m in markers:
            self.markers.append(m)
            self.markers_seen.append(m)
            if self.first_marker is None:
                self.first_marker = m
        self.markers.sort(key=lambda m: m.t)
        self.horizon = horizon

    # ------------------------------------------------------------------ reading, trimming
    def odometer_at(self, t: Array) -> Array:
        """Odometer distance (m) interpolated at times t (s, sorted), from the buffered
        readings."""
        o = self.odo
        if len(o) == 0:
            return np.zeros_like(t)
        i0 = max(int(np.searchsorted(o.t, t[0])) - 1, 0)
        i1 = int(np.searchsorted(o.t, t[-1])) + 1
        return np.interp(t, o.t[i0:i1], o.distance[i0:i1])

    def take_markers(self, t_end: float) -> list[Marker]:
        """The pending marker passages stamped at or before t_end (s), removed."""
        due = [m for m in self.markers if m.t <= t_end]
        for m in due:
            self.markers.remove(m)
        return due

    def drop_before(self, t: float) -> None:
        """Forget the samples an epoch ending at t (s) no longer needs: the IMU samples up to
        t, the odometer readings before the last one at or before STOP_MARGIN_S before it (the
        next epoch's stop test looks that far back), the magnetometer samples over MAG_KEEP_S
        before it."""
        i = int(np.searchsorted(self.imu_t, t, side="right"))
        # slices are views: O(1) per epoch whatever the length of the log
        self.imu_t, self.imu_g, self.imu_a = self.imu_t[i:], self.imu_g[i:], self.imu_a[i:]
        o = self.odo
        i = max(int(np.searchsorted(o.t, t - STOP_MARGIN_S)) - 1, 0)
        if i > 0:
            self.odo = o.slice(slice(i, None))
        mg = self.mag
        i = int(np.searchsorted(mg.t, t - MAG_KEEP_S, side="right"))
        if i > 0:
            self.mag = mg.slice(slice(i, None))


def _last_stamp(log: SensorLog) -> float:
    ends = [x.t[-1] for x in (log.imu, log.odometer, log.mag) if len(x)]
    return max(ends) if ends else -math.inf
