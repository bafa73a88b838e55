"""Baseline for comparison only: seed 002's complementary filter with odometer dead reckoning.

Attitude from the gyros (quaternion, base_link -> ENU) is pulled toward the accelerometer's roll
and pitch with gain ``k`` per sample (seed 002 eq. 7, k = 0.02); the accelerometer pitch is
corrected for the along-track acceleration dv/dt from the odometer (eq. 8-10). Heading comes
from the gyros only. Position is the odometer distance along the body x axis (eq. after 12).
The run starts at the first marker with the heading of the bearing to the second (as the
engine's alignment does) and uses no other marker: this is what the paper's method gives.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.filter import alignment
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.types import SensorLog, Trajectory, markers_sorted

Array = NDArray[np.float64]


def complementary_trajectory(
    log: SensorLog,
    *,
    k: float = 0.02,
    static_s: float = 2.0,
    block: int = 50,
    window: float = 0.5,
) -> Trajectory:
    """Baseline trajectory at the IMU sample times (IMU in base_link).

    k: blending gain per IMU sample toward the accelerometer roll/pitch; static_s: s of data at
    the start used to level and to remove the gyro bias; block: samples integrated between two
    blends (the gain is compounded to keep the per-sample k); window: s over which the odometer
    speed and acceleration are differenced (tick quantization makes shorter ones useless).
    """
    markers = markers_sorted(log.markers)
    if not markers:
        raise ValueError("the complementary baseline needs at least the launch marker")
    imu, odo = log.imu, log.odometer
    t = imu.t
    rest = t <= t[0] + static_s
    roll, pitch = alignment.level(imu.accel[rest].mean(axis=0))
    azimuth = alignment.marker_bearing(markers[0], markers[1])[0] if len(markers) > 1 else 0.0
    first = markers[0]
    c0 = att.dcm_from_euler(roll, pitch, azimuth)
    bias = alignment.gyro_bias_at_rest(imu.gyro[rest].mean(axis=0), c0, first.lat)
    q = att.quat_from_dcm(c0)
    dist = np.interp(t, odo.t, odo.distance) if len(odo) else np.zeros_like(t)
    speed = _windowed_rate(t, dist, window)
    accel_x = _windowed_rate(t, speed, window)
    g = earth.gravity(first.lat, first.alt)
    k_block = 1.0 - (1.0 - k) ** block
    quats = np.empty((len(t), 4))
    i = 0
    while i < len(t):
        j = min(i + block, len(t))
        dt = np.diff(np.r_[t[i - 1] if i else t[0], t[i:j]])
        dq = att.quat_from_rotvec((imu.gyro[i:j] - bias) * dt[:, None])
        qs = att.quat_cumprod(q, dq)
        # accelerometer attitude at the block end, pitch corrected for along-track acceleration
        f = imu.accel[j - 1]
        pitch_a = math.asin(float(np.clip((f[0] - accel_x[j - 1]) / g, -1.0, 1.0)))
        roll_a = math.atan2(f[1], f[2])
        r_g, p_g, a_g = att.euler_from_dcm(att.dcm_from_quat(qs[-1]))
        r_new = r_g + k_block * float(np.angle(np.exp(1j * (roll_a - r_g))))
        p_new = p_g + k_block * (pitch_a - p_g)
        q = att.quat_from_euler(r_new, p_new, a_g)
        qs[-1] = q
        quats[i:j] = qs
        i = j
    axis = att.body_x_axis(quats)
    step = np.diff(dist, prepend=dist[0])
    enu = np.cumsum(axis * step[:, None], axis=0)
    lat, lon, h = earth.enu_to_geodetic(enu, first.lat, first.lon, first.alt)
    vel = axis * speed[:, None]
    return Trajectory(t, lat, lon, h, vel, quats, dist - dist[0])


def _windowed_rate(t: Array, x: Array, window: float) -> Array:
    """Derivative of x(t) by central differences over +-window/2 (one-sided at the ends)."""
    lo = np.searchsorted(t, t - 0.5 * window)
    hi = np.minimum(np.searchsorted(t, t + 0.5 * window, side="right") - 1, len(t) - 1)
    span = t[hi] - t[lo]
    return np.where(span > 0, (x[hi] - x[lo]) / np.where(span > 0, span, 1.0), 0.0)
