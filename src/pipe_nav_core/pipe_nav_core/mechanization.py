"""Strapdown mechanization over a block of IMU samples (one filter epoch), vectorized.

Two modes (DESIGN.md):
- :func:`ins_block`: full strapdown INS in ENU with Earth rate, transport rate, Coriolis and
  normal gravity (seed 003), coning and sculling corrections;
- :func:`dr_block`: odometer dead reckoning (seed 001): attitude from the gyros, position from
  the odometer distance along the (boresight-corrected) body axis, with the wheel lever arm
  removed.

IMU samples follow INTERFACES.md: sample i holds the MEAN rate and specific force over
(t[i-1], t[i]], in base_link. ``earth_sign = -1`` runs the equations in reversed time (the
backward filter feeds time-reversed data: negated gyro, negated stamps).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import attitude as att
from . import earth
from .state import NavState, odometer_axis

Array = NDArray[np.float64]


@dataclass
class Carry:
    """Increments of the last sample of the previous block (for coning and sculling), base_link."""

    dtheta: Array
    dvel: Array

    @classmethod
    def zero(cls) -> Carry:
        return cls(np.zeros(3), np.zeros(3))


@dataclass
class BlockResult:
    """Per-sample trajectory of one block and the sums the filter needs for its transition matrix.

    t (M,) s; q_nb (M, 4); lat, lon (M,) rad; h (M,) m; vel_n (M, 3) m/s ENU.
    T: block duration, s. sum_c_dt: sum of C_nb dt (3, 3), s. dv_f: sum of C_nb (f - ba) dt (3,),
    m/s ENU. dp: ENU displacement over the block (3,), m. omega_b: mean bias-corrected body rate
    (3,), rad/s. mean_vel_b: mean body-frame velocity (3,), m/s. w_in: omega_in^n used (3,), rad/s.
    sum_c_w_dt (3, 9): sum of C_nb[:, i] omega_j dt, the coupling of the gyro error matrix;
    sum_c_f_dt (3, 9): sum of C_nb[:, i] f_j dt, the coupling of the accelerometer error matrix.
    DR only: dp_dk (3,) = d dp / d k; dp_dbore (3, 2); path (total |distance|, m).
    """

    t: Array
    q_nb: Array
    lat: Array
    lon: Array
    h: Array
    vel_n: Array
    T: float
    sum_c_dt: Array
    dv_f: Array
    dp: Array
    omega_b: Array
    f_mean_n: Array
    mean_vel_b: Array
    w_in: Array
    dp_dk: Array
    dp_dbore: Array
    path: float
    sum_c_w_dt: Array
    sum_c_f_dt: Array


def _dcm(q: Array) -> Array:
    """Rotation matrices (M, 3, 3) of unit quaternions (M, 4) [x, y, z, w] (as
    attitude.dcm_from_quat, filled in place: this runs once per filter epoch)."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    c = np.empty((len(q), 3, 3))
    c[:, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    c[:, 0, 1] = 2.0 * (x * y - w * z)
    c[:, 0, 2] = 2.0 * (x * z + w * y)
    c[:, 1, 0] = 2.0 * (x * y + w * z)
    c[:, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    c[:, 1, 2] = 2.0 * (y * z - w * x)
    c[:, 2, 0] = 2.0 * (x * z - w * y)
    c[:, 2, 1] = 2.0 * (y * z + w * x)
    c[:, 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return c


def _cross(a: Array, b: Array) -> Array:
    """Row-wise cross product of (M, 3) arrays (np.cross costs tens of microseconds a call)."""
    c = np.empty(np.broadcast_shapes(a.shape, b.shape))
    c[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    c[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    c[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return c


def _qmul(p: Array, q: Array) -> Array:
    """Hamilton product p * q of (M, 4) or (4,) scalar-last quaternions (as attitude.quat_mul)."""
    px, py, pz, pw = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty(np.broadcast_shapes(p.shape, q.shape))
    r[..., 0] = pw * qx + px * qw + py * qz - pz * qy
    r[..., 1] = pw * qy - px * qz + py * qw + pz * qx
    r[..., 2] = pw * qz + px * qy - py * qx + pz * qw
    r[..., 3] = pw * qw - px * qx - py * qy - pz * qz
    return r


def _cumprod(q0: Array, dq: Array) -> Array:
    """q0 * dq[0] * ... * dq[i] for every i (as attitude.quat_cumprod: log-depth prefix scan)."""
    acc = np.array(dq, dtype=np.float64)
    n = acc.shape[0]
    step = 1
    while step < n:
        acc[step:] = _qmul(acc[:-step].copy(), acc[step:])
        step *= 2
    return _qmul(np.asarray(q0, dtype=np.float64), acc)


def _attitudes(
    s: NavState, t: Array, gyro: Array, carry: Carry, w_in: Array
) -> tuple[Array, Array, Array, Array]:
    """Attitudes at the sample times, the previous-sample attitudes, raw and coned increments."""
    dt = np.diff(np.concatenate([[s.t], t]))
    rate = gyro - s.bg
    if np.any(s.gm):
        rate = np.linalg.solve(np.eye(3) + s.gm, rate.T).T
    dtheta = rate * dt[:, None]
    before = np.vstack([carry.dtheta[None, :], dtheta[:-1]])
    rv = dtheta + _cross(before, dtheta) / 12.0  # two-sample coning correction
    q_body = _cumprod(s.q_nb, att.quat_from_rotvec(rv))
    q_nav = att.quat_from_rotvec(-np.outer(t - s.t, w_in))
    q = _qmul(q_nav, q_body)
    q_prev = np.vstack([s.q_nb[None, :], q[:-1]])
    return q, q_prev, dtheta, dt


def ins_block(
    s: NavState, t: Array, gyro: Array, accel: Array, carry: Carry, earth_sign: float = 1.0
) -> tuple[NavState, BlockResult, Carry]:
    """Integrate the INS over samples (t, gyro, accel) from state s; returns the new state."""
    w_ie = earth_sign * earth.earth_rate_n(s.lat)
    w_en = earth.transport_rate_n(s.lat, s.h, s.vel_n)
    w_in = w_ie + w_en
    q, q_prev, dtheta, dt = _attitudes(s, t, gyro, carry, w_in)
    dvel = _specific_force(s, accel) * dt[:, None]
    th_before = np.vstack([carry.dtheta[None, :], dtheta[:-1]])
    dv_before = np.vstack([carry.dvel[None, :], dvel[:-1]])
    dv_b = (
        dvel
        + 0.5 * _cross(dtheta, dvel)
        + (_cross(th_before, dvel) + _cross(dv_before, dtheta)) / 12.0
    )
    c_all = _dcm(np.vstack([s.q_nb[None, :], q]))
    c_prev, c = c_all[:-1], c_all[1:]
    dv_f_n = np.einsum("mij,mj->mi", c_prev, dv_b)
    g = earth.gravity_n(s.lat, s.h)
    cor = g - np.cross(2.0 * w_ie + w_en, s.vel_n)
    vel = s.vel_n + np.cumsum(dv_f_n + np.outer(dt, cor), axis=0)
    vel_prev = np.vstack([s.vel_n[None, :], vel[:-1]])
    dp_i = 0.5 * (vel_prev + vel) * dt[:, None]
    p = np.cumsum(dp_i, axis=0)
    dlat, dlon, dh = earth.enu_to_geodetic_increment(p, s.lat, s.h)
    lat, lon, h = s.lat + dlat, s.lon + dlon, s.h + dh
    T = float(t[-1] - s.t)
    c_mid = 0.5 * (c + c_prev)
    sum_c_dt = np.einsum("mij,m->ij", c_mid, dt)
    vel_mid = 0.5 * (vel_prev + vel)
    mean_vel_b = np.einsum("mji,mj,m->i", c_mid, vel_mid, dt) / T
    dv_f = dv_f_n.sum(axis=0)
    new = s.copy()
    new.t = float(t[-1])
    new.odoq = np.array([s.odoq[1], 0.0])  # the end of this epoch starts the next one
    new.q_nb = att.quat_normalize(q[-1])
    new.vel_n = vel[-1].copy()
    new.lat, new.lon, new.h = float(lat[-1]), float(lon[-1]), float(h[-1])
    res = BlockResult(
        t=t,
        q_nb=q,
        lat=lat,
        lon=lon,
        h=h,
        vel_n=vel,
        T=T,
        sum_c_dt=sum_c_dt,
        dv_f=dv_f,
        dp=p[-1].copy(),
        omega_b=dtheta.sum(axis=0) / T,
        f_mean_n=dv_f / T,
        mean_vel_b=mean_vel_b,
        w_in=w_in,
        dp_dk=np.zeros(3),
        dp_dbore=np.zeros((3, 2)),
        path=float(np.abs(np.linalg.norm(dp_i, axis=1)).sum()),
        sum_c_w_dt=np.einsum("kai,kj->aij", c_mid, dtheta).reshape(3, 9),
        sum_c_f_dt=np.einsum("kai,kj->aij", c_prev, dvel).reshape(3, 9),
    )
    return new, res, Carry(dtheta[-1].copy(), dvel[-1].copy())


def _specific_force(s: NavState, accel: Array) -> Array:
    """Specific force (M, 3) m/s^2 from raw accelerometer samples: (I + N)^-1 (accel - ba)."""
    f = accel - s.ba
    if np.any(s.am):
        f = np.linalg.solve(np.eye(3) + s.am, f.T).T
    return f


def dr_block(
    s: NavState,
    t: Array,
    gyro: Array,
    accel: Array,
    ds: Array,
    carry: Carry,
    lever_arm: Array,
    earth_sign: float = 1.0,
) -> tuple[NavState, BlockResult, Carry]:
    """Odometer dead reckoning over one block.

    ds: (M,) raw odometer distance over each sample interval, m (wall contact point).
    lever_arm: (3,) m, wheel contact point in base_link; its rotation-induced motion is removed.
    """
    w_ie = earth_sign * earth.earth_rate_n(s.lat)
    vel_guess = s.vel_n
    w_in = w_ie + earth.transport_rate_n(s.lat, s.h, vel_guess)
    q, q_prev, dtheta, dt = _attitudes(s, t, gyro, carry, w_in)
    u, du = odometer_axis(s.bore)
    lever_x = dtheta[:, 1] * lever_arm[2] - dtheta[:, 2] * lever_arm[1]  # (omega x d)_x dt
    ds_c = (1.0 + s.k) * ds - lever_x
    c_all = _dcm(np.vstack([s.q_nb[None, :], q]))
    c_prev, c = c_all[:-1], c_all[1:]
    c_mid = 0.5 * (c + c_prev)
    cu = c_mid @ u  # (M, 3) odometer axis in ENU
    dp_i = cu * ds_c[:, None]
    p = np.cumsum(dp_i, axis=0)
    dlat, dlon, dh = earth.enu_to_geodetic_increment(p, s.lat, s.h)
    lat, lon, h = s.lat + dlat, s.lon + dlon, s.h + dh
    T = float(t[-1] - s.t)
    vel = dp_i / dt[:, None]
    f_b = _specific_force(s, accel)
    dv_f_n = np.einsum("mij,mj->mi", c_mid, f_b) * dt[:, None]
    new = s.copy()
    new.t = float(t[-1])
    new.q_nb = att.quat_normalize(q[-1])
    new.vel_n = p[-1] / T
    new.lat, new.lon, new.h = float(lat[-1]), float(lon[-1]), float(h[-1])
    res = BlockResult(
        t=t,
        q_nb=q,
        lat=lat,
        lon=lon,
        h=h,
        vel_n=vel,
        T=T,
        sum_c_dt=np.einsum("mij,m->ij", c_mid, dt),
        dv_f=dv_f_n.sum(axis=0),
        dp=p[-1].copy(),
        omega_b=dtheta.sum(axis=0) / T,
        f_mean_n=dv_f_n.sum(axis=0) / T,
        mean_vel_b=u * (ds_c.sum() / T),
        w_in=w_in,
        dp_dk=(cu * ds[:, None]).sum(axis=0),
        dp_dbore=(1.0 + s.k) * np.einsum("mij,jk,m->ik", c_mid, du, ds),
        path=float(np.abs(ds_c).sum()),
        sum_c_w_dt=np.einsum("kai,kj->aij", c_mid, dtheta).reshape(3, 9),
        sum_c_f_dt=np.einsum("kai,kj->aij", c_mid, f_b * dt[:, None]).reshape(3, 9),
    )
    dvel = f_b * dt[:, None]
    return new, res, Carry(dtheta[-1].copy(), dvel[-1].copy())
