"""Strapdown mechanization over a block of IMU samples (one filter epoch).

About 550 lines, one module on purpose: one job, the two modes' recursions over a block, from
the per-sample kernels up to the NavState blocks; every part is read with the others (a split
would cut the INS and dead-reckoning recursions from the step kernels that assemble them).

Two modes (DESIGN.md):
- :func:`ins_block`: full strapdown INS in ENU with Earth rate, transport rate, Coriolis and
  normal gravity (seed 003), coning and sculling corrections;
- :func:`dr_block`: odometer dead reckoning (seed 001): attitude from the gyros, position from
  the odometer distance along the (boresight-corrected) body axis, with the wheel lever arm
  removed.

IMU samples follow INTERFACES.md: sample i holds the MEAN rate and specific force over
(t[i-1], t[i]], in base_link. ``earth_sign = -1`` runs the equations in reversed time (the
backward filter feeds time-reversed data: negated gyro, negated stamps).

The per-sample recursions run in small kernels compiled with numba (``_attitude_k``,
``_ins_k``, ``_dr_k``: plain float64 arrays in and out); the public functions prepare
the per-block quantities (Earth and transport rates, gravity, odometer axis) and assemble the
results. The kernels are cached on disk (``cache=True``): the first call in a fresh process
loads them (or compiles them once, a few seconds, when the cache is cold or not writable).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.state import (
    I_AM,
    I_BA,
    I_BG,
    I_BORE,
    I_GM,
    I_ODOQ,
    I_Q,
    I_VEL,
    SV_H,
    SV_K,
    SV_LAT,
    SV_LON,
    SV_T,
    NavState,
    odometer_axis,
)

Array = NDArray[np.float64]


class Step(NamedTuple):
    """What :func:`ins_step_k` and :func:`dr_step_k` return for one block of M samples (the
    fields of :class:`BlockResult` they feed, in its units), compiled code's named record."""

    state: Array  # the flat state at the block end
    q_nb: Array  # (M, 4) attitude per sample
    lat: Array  # (M,) rad
    lon: Array  # (M,) rad
    h: Array  # (M,) m
    vel_n: Array  # (M, 3) m/s ENU
    T: float  # s, the block's length
    path: float  # m
    sum_c_dt: Array
    sum_c_w_dt: Array
    sum_c_f_dt: Array
    dv_f: Array
    dp: Array
    dp_dk: Array
    dp_dbore: Array
    omega_b: Array
    f_mean_n: Array
    mean_vel_b: Array
    w_in: Array
    carry: Array  # (6,) the block's last dtheta (rad) and dvel (m/s), for the next block


@dataclass
class Carry:
    """Increments of the last sample of the previous block (for coning and sculling), base_link.

    dtheta: (3,) angle increment, rad; dvel: (3,) specific-force velocity increment, m/s.
    """

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


@kernel
def _corrected(raw: Array, bias: Array, err: Array) -> Array:
    """Sensor samples corrected for bias and error matrix: (I + err)^-1 (raw - bias), (M, 3).

    raw (M, 3), bias (3,), err (3, 3): the gyro (rad/s) or accelerometer (m/s^2) model
    raw = (I + err) x + bias, base_link.
    """
    inv = att.inv3(np.eye(3) + err)
    out = np.empty_like(raw)
    for i in range(raw.shape[0]):
        x0 = raw[i, 0] - bias[0]
        x1 = raw[i, 1] - bias[1]
        x2 = raw[i, 2] - bias[2]
        for a in range(3):
            out[i, a] = inv[a, 0] * x0 + inv[a, 1] * x1 + inv[a, 2] * x2
    return out


# --- kernels: one pass over the samples of a block each ---


@kernel
def _attitude_k(
    q0: Array,
    t0: float,
    t: Array,
    gyro: Array,
    bg: Array,
    gm: Array,
    carry_dtheta: Array,
    w_in: Array,
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Attitude propagation over a block, with the attitude-only sums of the block.

    q0 (4,) q_nb at t0 (s); t (M,) sample times, s; gyro (M, 3) raw mean rates, rad/s,
    base_link; bg (3,) rad/s and gm (3, 3): gyro bias and error matrix; carry_dtheta (3,) the
    last angle increment of the previous block, rad; w_in (3,) omega_in^n, rad/s ENU, held over
    the block.

    Body increments dtheta = rate dt with the two-sample coning correction
    rv = dtheta + before x dtheta / 12 are chained on the right of q0; the navigation-frame
    rotation quat_from_rotvec(-(t - t0) w_in) is applied on the left.

    Returns q (M, 4) q_nb at the samples; c (M + 1, 3, 3) C_nb at t0 and at the samples;
    dtheta (M, 3) rad (uncorrected for coning); dt (M,) s; sum_c_dt (3, 3) sum of C_mid dt, s;
    sum_c_w_dt (3, 9) sum of C_mid[:, i] dtheta_j, rad; C_mid = (C_prev + C) / 2.
    """
    m = t.shape[0]
    rate = _corrected(gyro, bg, gm)
    q = np.empty((m, 4))
    c = np.empty((m + 1, 3, 3))
    dtheta = np.empty((m, 3))
    dt = np.empty(m)
    sum_c_dt = np.zeros((3, 3))
    sum_c_w_dt = np.zeros((3, 9))
    att.dcm_into((q0[0], q0[1], q0[2], q0[3]), c[0])
    body = (q0[0], q0[1], q0[2], q0[3])
    before = (carry_dtheta[0], carry_dtheta[1], carry_dtheta[2])
    t_prev = t0
    for k in range(m):
        dt[k] = t[k] - t_prev
        t_prev = t[k]
        d = (rate[k, 0] * dt[k], rate[k, 1] * dt[k], rate[k, 2] * dt[k])
        cone = att.cross3(before, d)
        dq = att.qrotvec(d[0] + cone[0] / 12.0, d[1] + cone[1] / 12.0, d[2] + cone[2] / 12.0)
        body = att.qmul(body, dq)
        tau = t[k] - t0
        nav = att.qrotvec(-(tau * w_in[0]), -(tau * w_in[1]), -(tau * w_in[2]))
        qk = att.qmul(nav, body)
        for a in range(4):
            q[k, a] = qk[a]
        for a in range(3):
            dtheta[k, a] = d[a]
        att.dcm_into(qk, c[k + 1])
        for a in range(3):
            for i in range(3):
                c_mid = 0.5 * (c[k + 1, a, i] + c[k, a, i])
                sum_c_dt[a, i] += c_mid * dt[k]
                for j in range(3):
                    sum_c_w_dt[a, 3 * i + j] += c_mid * d[j]
        before = d
    return q, c, dtheta, dt, sum_c_dt, sum_c_w_dt


@kernel
def _ins_k(
    c: Array,
    dtheta: Array,
    dt: Array,
    accel: Array,
    ba: Array,
    am: Array,
    carry_dtheta: Array,
    carry_dvel: Array,
    vel0: Array,
    g: Array,
    w_cor: Array,
) -> tuple[Array, Array, Array, Array, Array, float, Array]:
    """Velocity and position integration of the INS over a block.

    c (M + 1, 3, 3), dtheta (M, 3) rad and dt (M,) s from :func:`_attitude_k`; accel
    (M, 3) raw mean specific force, m/s^2 base_link; ba (3,) m/s^2 and am (3, 3): accelerometer
    bias and error matrix; carry_dtheta, carry_dvel (3,): the last increments of the previous
    block (rad, m/s); vel0 (3,) m/s ENU at the block start; g (3,) normal gravity, m/s^2 ENU,
    and w_cor (3,) = 2 omega_ie + omega_en, rad/s ENU, at the block start: gravity and the
    Coriolis acceleration cor = g - w_cor x vel0 are held over the block.

    Sculling: dv_b = dvel + dtheta x dvel / 2 + (th_before x dvel + dv_before x dtheta) / 12,
    rotated to ENU with C_nb of the previous sample; velocity v_k = v0 + sum (C dv_b + cor dt),
    position by the trapezoid rule.

    Returns vel (M, 3) m/s ENU; p (M, 3) ENU displacement from the block start, m; dvel (M, 3)
    specific-force increments, m/s base_link; dv_f (3,) sum of C_prev dv_b, m/s ENU; vel_b_dt
    (3,) sum of C_mid^T v_mid dt, m; path (sum of |dp|, m); sum_c_f_dt (3, 9) sum of
    C_prev[:, i] dvel_j, m/s.
    """
    m = dt.shape[0]
    f = _corrected(accel, ba, am)
    coriolis = att.cross3(w_cor, vel0)
    cor = (g[0] - coriolis[0], g[1] - coriolis[1], g[2] - coriolis[2])
    vel = np.empty((m, 3))
    p = np.empty((m, 3))
    dvel = np.empty((m, 3))
    dv_f = np.zeros(3)
    vel_b_dt = np.zeros(3)
    sum_c_f_dt = np.zeros((3, 9))
    path = 0.0
    th_before = (carry_dtheta[0], carry_dtheta[1], carry_dtheta[2])
    dv_before = (carry_dvel[0], carry_dvel[1], carry_dvel[2])
    v_prev = (vel0[0], vel0[1], vel0[2])
    dv_sum = (0.0, 0.0, 0.0)
    pos = (0.0, 0.0, 0.0)
    for k in range(m):
        d = (dtheta[k, 0], dtheta[k, 1], dtheta[k, 2])
        dv = (f[k, 0] * dt[k], f[k, 1] * dt[k], f[k, 2] * dt[k])
        rot = att.cross3(d, dv)
        s1 = att.cross3(th_before, dv)
        s2 = att.cross3(dv_before, d)
        dv_b = (
            dv[0] + 0.5 * rot[0] + (s1[0] + s2[0]) / 12.0,
            dv[1] + 0.5 * rot[1] + (s1[1] + s2[1]) / 12.0,
            dv[2] + 0.5 * rot[2] + (s1[2] + s2[2]) / 12.0,
        )
        cp = c[k]
        dv_n = (
            cp[0, 0] * dv_b[0] + cp[0, 1] * dv_b[1] + cp[0, 2] * dv_b[2],
            cp[1, 0] * dv_b[0] + cp[1, 1] * dv_b[1] + cp[1, 2] * dv_b[2],
            cp[2, 0] * dv_b[0] + cp[2, 1] * dv_b[1] + cp[2, 2] * dv_b[2],
        )
        dv_sum = (
            dv_sum[0] + (dv_n[0] + dt[k] * cor[0]),
            dv_sum[1] + (dv_n[1] + dt[k] * cor[1]),
            dv_sum[2] + (dv_n[2] + dt[k] * cor[2]),
        )
        v = (vel0[0] + dv_sum[0], vel0[1] + dv_sum[1], vel0[2] + dv_sum[2])
        v_mid = (0.5 * (v_prev[0] + v[0]), 0.5 * (v_prev[1] + v[1]), 0.5 * (v_prev[2] + v[2]))
        dp = (v_mid[0] * dt[k], v_mid[1] * dt[k], v_mid[2] * dt[k])
        pos = (pos[0] + dp[0], pos[1] + dp[1], pos[2] + dp[2])
        path += np.sqrt(dp[0] * dp[0] + dp[1] * dp[1] + dp[2] * dp[2])
        for a in range(3):
            vel[k, a] = v[a]
            p[k, a] = pos[a]
            dvel[k, a] = dv[a]
            dv_f[a] += dv_n[a]
        for i in range(3):
            vb = 0.0
            for a in range(3):
                c_mid = 0.5 * (c[k + 1, a, i] + cp[a, i])
                vb += c_mid * v_mid[a]
                for j in range(3):
                    sum_c_f_dt[a, 3 * i + j] += cp[a, i] * dv[j]
            vel_b_dt[i] += vb * dt[k]
        th_before = d
        dv_before = dv
        v_prev = v
    return vel, p, dvel, dv_f, vel_b_dt, path, sum_c_f_dt


@kernel
def _dr_k(
    c: Array,
    dtheta: Array,
    dt: Array,
    accel: Array,
    ba: Array,
    am: Array,
    ds: Array,
    scale: float,
    lever_arm: Array,
    u: Array,
    du: Array,
) -> tuple[Array, Array, Array, Array, float, float, Array, Array, Array]:
    """Odometer dead-reckoning position over a block.

    c (M + 1, 3, 3), dtheta (M, 3) rad and dt (M,) s from :func:`_attitude_k`; accel
    (M, 3) raw mean specific force, m/s^2 base_link; ba (3,) m/s^2 and am (3, 3): accelerometer
    bias and error matrix; ds (M,) raw odometer distance increments, m; scale = 1 + k;
    lever_arm (3,) m, wheel contact point in base_link; u (3,) odometer axis in base_link and
    du (3, 2) its derivative with respect to the boresight (yaw, pitch).

    The distance along the axis, ds_c = scale ds - (dtheta x lever_arm)_x, is laid along
    C_mid u (C_mid = (C_prev + C) / 2).

    Returns vel (M, 3) m/s ENU (dp / dt); p (M, 3) ENU displacement from the block start, m;
    dvel (M, 3) specific-force increments f dt, m/s base_link; dv_f (3,) sum of C_mid f dt, m/s
    ENU; ds_c_sum (m); path (sum of |ds_c|, m); dp_dk (3,) sum of C_mid u ds, m; dp_dbore (3, 2)
    scale * sum of C_mid du ds, m/rad; sum_c_f_dt (3, 9) sum of C_mid[:, i] f_j dt, m/s.
    """
    m = dt.shape[0]
    f = _corrected(accel, ba, am)
    vel = np.empty((m, 3))
    p = np.empty((m, 3))
    dvel = np.empty((m, 3))
    dv_f = np.zeros(3)
    dp_dk = np.zeros(3)
    c_ds = np.zeros((3, 3))
    sum_c_f_dt = np.zeros((3, 9))
    ds_c_sum = 0.0
    path = 0.0
    c_mid = np.empty((3, 3))
    pos = np.zeros(3)
    for k in range(m):
        lever_x = dtheta[k, 1] * lever_arm[2] - dtheta[k, 2] * lever_arm[1]  # (omega x d)_x dt
        ds_c = scale * ds[k] - lever_x
        ds_c_sum += ds_c
        path += abs(ds_c)
        fk = (f[k, 0], f[k, 1], f[k, 2])
        for a in range(3):
            dvel[k, a] = fk[a] * dt[k]
        for a in range(3):
            for i in range(3):
                c_mid[a, i] = 0.5 * (c[k + 1, a, i] + c[k, a, i])
            cu = c_mid[a, 0] * u[0] + c_mid[a, 1] * u[1] + c_mid[a, 2] * u[2]
            cf = c_mid[a, 0] * fk[0] + c_mid[a, 1] * fk[1] + c_mid[a, 2] * fk[2]
            dp = cu * ds_c
            pos[a] += dp
            p[k, a] = pos[a]
            vel[k, a] = dp / dt[k]
            dp_dk[a] += cu * ds[k]
            dv_f[a] += cf * dt[k]
            for i in range(3):
                c_ds[a, i] += c_mid[a, i] * ds[k]
                for j in range(3):
                    sum_c_f_dt[a, 3 * i + j] += c_mid[a, i] * dvel[k, j]
    dp_dbore = scale * (c_ds @ du)
    return vel, p, dvel, dv_f, ds_c_sum, path, dp_dk, dp_dbore, sum_c_f_dt


def _f64(a: Array) -> Array:
    """a as a C-contiguous float64 array (no copy when it already is one): one kernel
    specialization serves every caller."""
    return np.ascontiguousarray(a, dtype=np.float64)


@kernel
def _rates(sv: Array, earth_sign: float) -> tuple[Array, Array, float, float]:
    """Earth rate and transport rate (rad/s ENU) and the radii R_M, R_N (m) at the flat state."""
    lat, h = sv[SV_LAT], sv[SV_H]
    w_ie = earth.earth_rate_k(lat, earth_sign)
    rm, rn = earth._radii(lat)
    w_en = earth.transport_rate_k(lat, h, sv[I_VEL], sv[I_VEL + 1])
    return w_ie, w_en, rm, rn


@kernel
def _end_state(
    sv: Array, t: Array, q: Array, p: Array, rm: float, rn: float
) -> tuple[Array, Array, Array, Array]:
    """Per-sample geodetic position (lat, lon rad, h m) at ENU displacements p (M, 3) from sv,
    and sv moved to the last sample (time, attitude, position)."""
    lat0, h0 = sv[SV_LAT], sv[SV_H]
    lat = lat0 + p[:, 1] / (rm + h0)
    lon = sv[SV_LON] + p[:, 0] / ((rn + h0) * np.cos(lat0))
    h = h0 + p[:, 2]
    out = sv.copy()
    out[SV_T] = t[-1]
    qn = att.qnormalize((q[-1, 0], q[-1, 1], q[-1, 2], q[-1, 3]))
    for i in range(4):
        out[I_Q + i] = qn[i]
    out[SV_LAT], out[SV_LON], out[SV_H] = lat[-1], lon[-1], h[-1]
    return lat, lon, h, out


@kernel
def _attitude(
    sv: Array, t: Array, gyro: Array, carry: Array, w_in: Array
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """_attitude_k from the flat state sv (its attitude, time, gyro bias and matrix)."""
    gm = sv[I_GM : I_GM + 9].copy().reshape(3, 3)
    q0, bg = sv[I_Q : I_Q + 4], sv[I_BG : I_BG + 3]
    return _attitude_k(q0, sv[SV_T], t, gyro, bg, gm, carry[:3], w_in)


@kernel
def ins_step_k(
    sv: Array, t: Array, gyro: Array, accel: Array, carry: Array, earth_sign: float
) -> Step:
    """The strapdown INS over one block from the flat state sv (see :func:`ins_block`;
    carry (6,) = the previous block's last dtheta, dvel). Returns :data:`Step`."""
    w_ie, w_en, rm, rn = _rates(sv, earth_sign)
    w_in = w_ie + w_en
    q, c, dtheta, dt, sum_c_dt, sum_c_w_dt = _attitude(sv, t, gyro, carry, w_in)
    g = np.array([0.0, 0.0, -earth._gravity(sv[SV_LAT], sv[SV_H])])
    am = sv[I_AM : I_AM + 9].copy().reshape(3, 3)
    vel, p, dvel, dv_f, vel_b_dt, path, sum_c_f_dt = _ins_k(
        c,
        dtheta,
        dt,
        accel,
        sv[I_BA : I_BA + 3],
        am,
        carry[:3],
        carry[3:],
        sv[I_VEL : I_VEL + 3],
        g,
        2.0 * w_ie + w_en,
    )
    lat, lon, h, out = _end_state(sv, t, q, p, rm, rn)
    out[I_ODOQ], out[I_ODOQ + 1] = sv[I_ODOQ + 1], 0.0  # this epoch's end starts the next one
    out[I_VEL : I_VEL + 3] = vel[-1]
    T = t[-1] - sv[SV_T]
    return Step(
        out, q, lat, lon, h, vel, T, path,
        sum_c_dt, sum_c_w_dt, sum_c_f_dt, dv_f, p[-1].copy(), np.zeros(3), np.zeros((3, 2)),
        dtheta.sum(axis=0) / T, dv_f / T, vel_b_dt / T, w_in,
        np.concatenate((dtheta[-1], dvel[-1])),
    )  # fmt: skip


@kernel
def dr_step_k(
    sv: Array,
    t: Array,
    gyro: Array,
    accel: Array,
    ds: Array,
    carry: Array,
    lever_arm: Array,
    earth_sign: float,
) -> Step:
    """Odometer dead reckoning over one block from the flat state sv (see :func:`dr_block`;
    carry (6,) = the previous block's last dtheta, dvel). Returns :data:`Step`."""
    w_ie, w_en, rm, rn = _rates(sv, earth_sign)
    w_in = w_ie + w_en
    q, c, dtheta, dt, sum_c_dt, sum_c_w_dt = _attitude(sv, t, gyro, carry, w_in)
    u, du = odometer_axis(sv[I_BORE : I_BORE + 2])
    am = sv[I_AM : I_AM + 9].copy().reshape(3, 3)
    vel, p, dvel, dv_f, ds_c_sum, path, dp_dk, dp_dbore, sum_c_f_dt = _dr_k(
        c, dtheta, dt, accel, sv[I_BA : I_BA + 3], am, ds, 1.0 + sv[SV_K], lever_arm, u, du
    )
    lat, lon, h, out = _end_state(sv, t, q, p, rm, rn)
    T = t[-1] - sv[SV_T]
    out[I_VEL : I_VEL + 3] = p[-1] / T
    return Step(
        out, q, lat, lon, h, vel, T, path,
        sum_c_dt, sum_c_w_dt, sum_c_f_dt, dv_f, p[-1].copy(), dp_dk, dp_dbore,
        dtheta.sum(axis=0) / T, dv_f / T, u * (ds_c_sum / T), w_in,
        np.concatenate((dtheta[-1], dvel[-1])),
    )  # fmt: skip


def _block(s: NavState, t: Array, step: Step) -> tuple[NavState, BlockResult, Carry]:
    new = NavState.from_vector(step.state)
    new.distance = s.distance
    res = BlockResult(
        t=t,
        q_nb=step.q_nb,
        lat=step.lat,
        lon=step.lon,
        h=step.h,
        vel_n=step.vel_n,
        T=float(step.T),
        sum_c_dt=step.sum_c_dt,
        dv_f=step.dv_f,
        dp=step.dp,
        omega_b=step.omega_b,
        f_mean_n=step.f_mean_n,
        mean_vel_b=step.mean_vel_b,
        w_in=step.w_in,
        dp_dk=step.dp_dk,
        dp_dbore=step.dp_dbore,
        path=float(step.path),
        sum_c_w_dt=step.sum_c_w_dt,
        sum_c_f_dt=step.sum_c_f_dt,
    )
    carry = step.carry
    return new, res, Carry(carry[:3].copy(), carry[3:].copy())


def ins_block(
    s: NavState, t: Array, gyro: Array, accel: Array, carry: Carry, earth_sign: float = 1.0
) -> tuple[NavState, BlockResult, Carry]:
    """Integrate the strapdown INS over one block of IMU samples from state s.

    t: (M,) sample times, s (after s.t); gyro: (M, 3) mean angular rates, rad/s base_link;
    accel: (M, 3) mean specific forces, m/s^2 base_link; carry: the last increments of the
    previous block; earth_sign: -1 for time-reversed data. Returns the state at t[-1], the
    per-sample trajectory and block sums, and the carry for the next block.
    """
    t = _f64(t)
    c = np.concatenate([carry.dtheta, carry.dvel])
    return _block(s, t, ins_step_k(s.vector(), t, _f64(gyro), _f64(accel), c, earth_sign))


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
    """Odometer dead reckoning over one block of IMU samples from state s.

    t: (M,) sample times, s (after s.t); gyro: (M, 3) mean angular rates, rad/s base_link;
    accel: (M, 3) mean specific forces, m/s^2 base_link (for the filter's sums only);
    ds: (M,) raw odometer distance over each sample interval, m (wall contact point);
    carry: the last increments of the previous block; lever_arm: (3,) m, wheel contact point
    in base_link, its rotation-induced motion is removed; earth_sign: -1 for time-reversed
    data. Returns the state at t[-1], the per-sample trajectory and block sums, and the carry.
    """
    t = _f64(t)
    c = np.concatenate([carry.dtheta, carry.dvel])
    step = dr_step_k(
        s.vector(), t, _f64(gyro), _f64(accel), _f64(ds), c, _f64(lever_arm), earth_sign
    )
    return _block(s, t, step)
