"""Measurement models: one contract shared by the forward filter, the backward filter and the
smoothers.

Each model returns a :class:`Measurement` with
- ``residual`` r = z - h(x_hat) (m,),
- ``H`` (m, n) with r ~= H dx + noise for the error state dx = truth - estimate
  (conventions in :mod:`pipe_nav_core.state`),
- ``R`` (m, m) the noise covariance, in the measurement's units.

Frames: ENU navigation frame, base_link body frame (FLU). Units SI, angles rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import earth
from .state import Layout, NavState, odometer_axis, skew3
from .types import Marker

Array = NDArray[np.float64]


@dataclass
class Measurement:
    """One update: name (for statistics), residual (m,), H (m, n), R (m, m)."""

    name: str
    residual: Array
    H: Array
    R: Array

    def rows(self, idx: list[int], name: str) -> Measurement:
        """The measurement restricted to some of its components, renamed."""
        return Measurement(name, self.residual[idx], self.H[idx], self.R[idx][:, idx])


def odometer_velocity(
    s: NavState,
    layout: Layout,
    *,
    speed: float,
    vel_b_offset: Array,
    lever_rate: float,
    sigma_speed: float,
    sigma_nhc: float,
    vel_jac: Array | None = None,
    epoch_s: float = 0.0,
) -> Measurement:
    """Odometer speed with the non-holonomic constraint (INS mode), body frame, m/s.

    The mean body velocity over the epoch must equal u(bore) * ((1 + k) * speed - lever_rate):
    speed is the raw mean odometer speed (distance increment / epoch duration), lever_rate the
    mean (omega x d)_x of the wheel contact point, vel_b_offset the difference between the
    block's mean body velocity and C_bn v_n at the epoch end (so that H refers to the end).
    vel_jac: ENU velocity (m/s) at which the attitude column of H is evaluated (default s.vel_n);
    the engine passes its first estimate so that a rotation of the whole solution about the
    vertical stays unobservable, as it truly is (first-estimate Jacobian).
    epoch_s: the epoch duration (s) over which speed was measured; with it and a layout that
    has odometer reading errors (odoq, m), speed is corrected by -(odoq_end - odoq_start) /
    epoch_s (the quantization of the readings at both ends of the epoch).
    """
    c = s.c_nb
    u, du = odometer_axis(s.bore)
    q = layout.odoq is not None and epoch_s > 0.0
    if q:
        speed = speed - (s.odoq[1] - s.odoq[0]) / epoch_s
    v_centre = (1.0 + s.k) * speed - lever_rate
    h = c.T @ s.vel_n + vel_b_offset - u * v_centre
    H = np.zeros((3, layout.n))
    assert layout.vel is not None
    H[:, layout.vel] = c.T
    H[:, layout.att] = c.T @ skew3(s.vel_n if vel_jac is None else vel_jac)
    H[:, layout.k] = (-u * speed)[:, None]
    H[:, layout.bore] = -v_centre * du
    if q:
        assert layout.odoq is not None
        H[:, layout.odoq.start] = -u * (1.0 + s.k) / epoch_s
        H[:, layout.odoq.start + 1] = u * (1.0 + s.k) / epoch_s
    R = np.diag([sigma_speed**2, sigma_nhc**2, sigma_nhc**2])
    return Measurement("odometer", -h, H, R)


def zero_velocity(s: NavState, layout: Layout, sigma: float) -> Measurement:
    """Zero velocity when stopped (INS mode): v_n = 0, m/s."""
    assert layout.vel is not None
    H = np.zeros((3, layout.n))
    H[:, layout.vel] = np.eye(3)
    return Measurement("zupt", -s.vel_n.copy(), H, np.eye(3) * sigma**2)


def zero_rate(
    s: NavState, layout: Layout, *, gyro_mean: Array, sigma: float, earth_sign: float = 1.0
) -> Measurement:
    """Zero angular rate when stopped: the mean gyro reading (rad/s, base_link) equals the
    Earth rate seen in the body plus the gyro bias."""
    c = s.c_nb
    w_ie = earth_sign * earth.earth_rate_n(s.lat)
    h = gyro_mean - s.bg - c.T @ w_ie
    H = np.zeros((3, layout.n))
    H[:, layout.bg] = -np.eye(3)
    H[:, layout.att] = -c.T @ skew3(w_ie)
    return Measurement("zaru", -h, H, np.eye(3) * sigma**2)


def gravity_tilt(
    s: NavState,
    layout: Layout,
    *,
    f_mean_n: Array,
    c_mean: Array,
    accel_n: Array,
    sigma: float,
    c_f_mean: Array | None = None,
) -> Measurement:
    """Gravity tilt (seed 001 eq. 11-13): the mean specific force rotated into ENU equals the
    kinematic acceleration plus the reaction to gravity, m/s^2.

    f_mean_n: mean C_nb (f - ba) over the epoch; c_mean: mean C_nb over the epoch; accel_n: the
    kinematic acceleration from the odometer and attitude (ENU). An attitude error rotates
    both the specific force and the kinematic acceleration (the odometer's path is laid out
    with the same attitude), so only their difference, the gravity reaction, sees it: the
    update constrains the tilt and, rightly, never the heading. c_f_mean (3, 9): mean of
    C_nb[:, i] f_j over the epoch, the coupling of the accelerometer error matrix (when the
    layout has it).
    """
    g = earth.gravity(s.lat, s.h)
    h = f_mean_n - accel_n - np.array([0.0, 0.0, g])
    H = np.zeros((3, layout.n))
    H[:, layout.att] = -skew3(f_mean_n - accel_n)
    H[:, layout.ba] = -c_mean
    if layout.am is not None and c_f_mean is not None:
        H[:, layout.am] = -c_f_mean
    return Measurement("tilt", -h, H, np.eye(3) * sigma**2)


def magnetic_heading(
    s: NavState,
    layout: Layout,
    *,
    field_b: Array,
    c_nb: Array,
    declination: float,
    sigma: float,
) -> Measurement:
    """Magnetic heading (seed 001 eq. 10): the horizontal direction of the measured field,
    rotated into ENU with the estimated attitude, equals magnetic north (declination east of
    true north positive), rad. field_b: hard-iron corrected field in base_link (tesla);
    c_nb: the attitude at the magnetometer sample time."""
    m = c_nb @ field_b
    rho2 = m[0] ** 2 + m[1] ** 2
    az = np.arctan2(m[0], m[1])
    h = np.array([np.angle(np.exp(1j * (az - declination)))])
    g = np.array([m[1], -m[0], 0.0]) / rho2
    H = np.zeros((1, layout.n))
    H[0, layout.att] = -g @ skew3(m)
    return Measurement("mag", -h, H, np.array([[sigma**2]]))


def marker_fix(s: NavState, layout: Layout, marker: Marker, *, time_sigma: float) -> Measurement:
    """Surveyed marker position versus the estimate at the passage time, ENU m.

    The nominal position is extrapolated from s.t to marker.t with the current velocity
    (|marker.t - s.t| is at most one IMU interval here); the passage-time uncertainty adds
    speed * time_sigma along the track.
    """
    dt = marker.t - s.t
    rm, rn = earth.radii(s.lat)
    d_enu = (
        np.array(
            [
                (marker.lon - s.lon) * (rn + s.h) * np.cos(s.lat),
                (marker.lat - s.lat) * (rm + s.h),
                marker.alt - s.h,
            ]
        )
        - s.vel_n * dt
    )
    H = np.zeros((3, layout.n))
    H[:, layout.pos] = np.eye(3)
    R = np.diag(np.square(marker.sigma_enu)) + time_sigma**2 * np.outer(s.vel_n, s.vel_n)
    return Measurement("marker", d_enu, H, R)
