"""Measurement models: one contract shared by the forward filter, the backward filter and the
smoothers.

Each model returns a :class:`Measurement` with
- ``residual`` r = z - h(x_hat) (m,),
- ``H`` (m, n) with r ~= H dx + noise for the error state dx = truth - estimate
  (conventions in :mod:`pipe_nav_core.state`),
- ``R`` (m, m) the noise covariance, in the measurement's units.

Frames: ENU navigation frame, base_link body frame (FLU). Units SI, angles rad.

Each model is a compiled kernel (``*_k``: flat state and layout index array, see
:mod:`pipe_nav_core.state`) returning (residual, H, R), which the engine's compiled epoch calls
directly; the functions without the suffix wrap it for NavState callers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import attitude as att
from . import earth
from .jit import kernel
from .state import (
    I_BG,
    I_BORE,
    I_ODOQ,
    I_VEL,
    L_AM,
    L_ATT,
    L_BA,
    L_BG,
    L_BORE,
    L_K,
    L_N,
    L_ODOQ,
    L_POS,
    L_VEL,
    SV_H,
    SV_K,
    SV_LAT,
    SV_LON,
    SV_T,
    Layout,
    NavState,
    c_nb_k,
    odometer_axis,
)
from .types import Marker

Array = NDArray[np.float64]
Index = NDArray[np.int64]
Model = tuple[Array, Array, Array]  # residual (m,), H (m, n), R (m, m)


@dataclass
class Measurement:
    """One update: name (for statistics), residual (m,), H (m, n), R (m, m)."""

    name: str
    residual: Array
    H: Array
    R: Array


@kernel
def odometer_velocity_k(
    sv: Array,
    L: Index,
    speed: float,
    vel_b_offset: Array,
    lever_rate: float,
    sigma_speed: float,
    sigma_nhc: float,
    vel_jac: Array,
    epoch_s: float,
) -> Model:
    """:func:`odometer_velocity` on a flat state (vel_jac required)."""
    c = c_nb_k(sv)
    u, du = odometer_axis(sv[I_BORE : I_BORE + 2])
    k = sv[SV_K]
    quantized = L[L_ODOQ] >= 0 and epoch_s > 0.0
    if quantized:
        speed = speed - (sv[I_ODOQ + 1] - sv[I_ODOQ]) / epoch_s
    v_centre = (1.0 + k) * speed - lever_rate
    vel = sv[I_VEL : I_VEL + 3]
    h = c.T @ vel + vel_b_offset - u * v_centre
    H = np.zeros((3, L[L_N]))
    v, a = L[L_VEL], L[L_ATT]
    H[:, v : v + 3] = c.T
    H[:, a : a + 3] = c.T @ att.skew_k(vel_jac)
    for r in range(3):
        H[r, L[L_K]] = -u[r] * speed
        H[r, L[L_BORE]] = -v_centre * du[r, 0]
        H[r, L[L_BORE] + 1] = -v_centre * du[r, 1]
        if quantized:
            H[r, L[L_ODOQ]] = -u[r] * (1.0 + k) / epoch_s
            H[r, L[L_ODOQ] + 1] = u[r] * (1.0 + k) / epoch_s
    R = np.diag(np.array([sigma_speed**2, sigma_nhc**2, sigma_nhc**2]))
    return -h, H, R


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
    assert layout.vel is not None
    r, H, R = odometer_velocity_k(
        s.vector(),
        layout.index,
        float(speed),
        np.asarray(vel_b_offset, dtype=np.float64),
        float(lever_rate),
        float(sigma_speed),
        float(sigma_nhc),
        np.asarray(s.vel_n if vel_jac is None else vel_jac, dtype=np.float64),
        float(epoch_s),
    )
    return Measurement("odometer", r, H, R)


@kernel
def zero_velocity_k(sv: Array, L: Index, sigma: float) -> Model:
    """:func:`zero_velocity` on a flat state."""
    H = np.zeros((3, L[L_N]))
    for r in range(3):
        H[r, L[L_VEL] + r] = 1.0
    return -sv[I_VEL : I_VEL + 3].copy(), H, np.eye(3) * sigma**2


def zero_velocity(s: NavState, layout: Layout, sigma: float) -> Measurement:
    """Zero velocity when stopped (INS mode): v_n = 0, m/s."""
    assert layout.vel is not None
    return Measurement("zupt", *zero_velocity_k(s.vector(), layout.index, float(sigma)))


@kernel
def zero_rate_k(sv: Array, L: Index, gyro_mean: Array, sigma: float, earth_sign: float) -> Model:
    """:func:`zero_rate` on a flat state."""
    c = c_nb_k(sv)
    w_ie = earth.earth_rate_k(sv[SV_LAT], earth_sign)
    h = gyro_mean - sv[I_BG : I_BG + 3] - c.T @ w_ie
    H = np.zeros((3, L[L_N]))
    for r in range(3):
        H[r, L[L_BG] + r] = -1.0
    a = L[L_ATT]
    H[:, a : a + 3] = -(c.T @ att.skew_k(w_ie))
    return -h, H, np.eye(3) * sigma**2


def zero_rate(
    s: NavState, layout: Layout, *, gyro_mean: Array, sigma: float, earth_sign: float = 1.0
) -> Measurement:
    """Zero angular rate when stopped: the mean gyro reading (rad/s, base_link) equals the
    Earth rate seen in the body plus the gyro bias."""
    r, H, R = zero_rate_k(
        s.vector(),
        layout.index,
        np.asarray(gyro_mean, dtype=np.float64),
        float(sigma),
        float(earth_sign),
    )
    return Measurement("zaru", r, H, R)


@kernel
def gravity_tilt_k(
    sv: Array,
    L: Index,
    f_mean_n: Array,
    c_mean: Array,
    accel_n: Array,
    sigma: float,
    c_f_mean: Array,
) -> Model:
    """:func:`gravity_tilt` on a flat state (c_f_mean (3, 9), or (0, 9) for none)."""
    g = earth._gravity(sv[SV_LAT], sv[SV_H])
    d = f_mean_n - accel_n
    h = d - np.array([0.0, 0.0, g])
    H = np.zeros((3, L[L_N]))
    a, ba, am = L[L_ATT], L[L_BA], L[L_AM]
    H[:, a : a + 3] = -att.skew_k(d)
    H[:, ba : ba + 3] = -c_mean
    if am >= 0 and c_f_mean.shape[0] == 3:
        H[:, am : am + 9] = -c_f_mean
    return -h, H, np.eye(3) * sigma**2


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
    f = np.asarray
    r, H, R = gravity_tilt_k(
        s.vector(),
        layout.index,
        f(f_mean_n, dtype=np.float64),
        f(c_mean, dtype=np.float64),
        f(accel_n, dtype=np.float64),
        float(sigma),
        np.zeros((0, 9)) if c_f_mean is None else f(c_f_mean, dtype=np.float64),
    )
    return Measurement("tilt", r, H, R)


@kernel
def magnetic_heading_k(
    sv: Array, L: Index, field_b: Array, c_nb: Array, declination: float, sigma: float
) -> Model:
    """:func:`magnetic_heading` on a flat state."""
    m = c_nb @ field_b
    rho2 = m[0] ** 2 + m[1] ** 2
    x = np.arctan2(m[0], m[1]) - declination
    h = np.array([np.arctan2(np.sin(x), np.cos(x))])
    g = np.array([m[1], -m[0], 0.0]) / rho2
    H = np.zeros((1, L[L_N]))
    a = L[L_ATT]
    H[0, a : a + 3] = -(g @ att.skew_k(m))
    return -h, H, np.array([[sigma**2]])


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
    r, H, R = magnetic_heading_k(
        s.vector(),
        layout.index,
        np.asarray(field_b, dtype=np.float64),
        np.ascontiguousarray(c_nb, dtype=np.float64),
        float(declination),
        float(sigma),
    )
    return Measurement("mag", r, H, R)


@kernel
def marker_fix_k(sv: Array, L: Index, marker: Array, time_sigma: float) -> Model:
    """:func:`marker_fix` on a flat state; marker = [t s, lat rad, lon rad, alt m, sigma E, N,
    U m] (:func:`marker_vector`)."""
    dt = marker[0] - sv[SV_T]
    lat, h = sv[SV_LAT], sv[SV_H]
    rm, rn = earth._radii(lat)
    vel = sv[I_VEL : I_VEL + 3]
    d_enu = np.empty(3)
    d_enu[0] = (marker[2] - sv[SV_LON]) * (rn + h) * np.cos(lat) - vel[0] * dt
    d_enu[1] = (marker[1] - lat) * (rm + h) - vel[1] * dt
    d_enu[2] = marker[3] - h - vel[2] * dt
    H = np.zeros((3, L[L_N]))
    for r in range(3):
        H[r, L[L_POS] + r] = 1.0
    R = np.diag(marker[4:7] ** 2) + time_sigma**2 * np.outer(vel, vel)
    return d_enu, H, R


def marker_vector(m: Marker) -> Array:
    """A marker as the flat vector marker_fix_k takes."""
    return np.array([m.t, m.lat, m.lon, m.alt, *m.sigma_enu], dtype=np.float64)


def marker_fix(s: NavState, layout: Layout, marker: Marker, *, time_sigma: float) -> Measurement:
    """Surveyed marker position versus the estimate at the passage time, ENU m.

    The nominal position is extrapolated from s.t to marker.t with the current velocity
    (|marker.t - s.t| is at most one IMU interval here); the passage-time uncertainty adds
    speed * time_sigma along the track.
    """
    r, H, R = marker_fix_k(s.vector(), layout.index, marker_vector(marker), float(time_sigma))
    return Measurement("marker", r, H, R)
