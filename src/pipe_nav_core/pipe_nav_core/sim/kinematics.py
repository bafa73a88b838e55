"""Exact kinematics of the pig and the ideal inertial signals it produces.

Given the pipe geometry and the pig motion, the state at time t is closed form: the body frame
``base_link`` has x along the pipe axis and is rolled by phi about it, so

    C_nb = dcm_from_euler(phi, theta(s), psi(s)),           v_n = s' u(s),
    dv_n/dt = s'' u + s'^2 du/ds,                           (components in local ENU)
    omega_nb^b from the Euler-angle rates (phi', theta' = kv s', psi' = kh s'),

and the ideal sensor outputs are (Earth rate, transport rate, normal gravity from earth.py)

    omega_ib^b = omega_nb^b + C_bn (omega_ie^n + omega_en^n),
    f^b        = C_bn (dv_n/dt + (2 omega_ie^n + omega_en^n) x v_n - g^n).

:func:`interval_means` averages them over sample intervals with 5-point Gauss-Lobatto quadrature
(exact for polynomials of degree 7), which is how integrating IMUs define their output; an
interval a short feature passes through (:func:`short_feature_intervals`) is averaged over
finer sub-intervals instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.geo import earth
from pipe_nav_core.geo.attitude import dcm_from_euler, quat_mul, quat_normalize
from pipe_nav_core.sim.geometry import PipeGeometry
from pipe_nav_core.sim.motion import PigMotion

FloatArray = NDArray[np.float64]

# 5-point Gauss-Lobatto rule on [-1, 1].
LOBATTO_X = np.array([-1.0, -math.sqrt(3.0 / 7.0), 0.0, math.sqrt(3.0 / 7.0), 1.0])
LOBATTO_W = np.array([0.1, 49.0 / 90.0, 32.0 / 45.0, 49.0 / 90.0, 0.1])
# A feature passed in fewer sample intervals than this is averaged over SUB_INTERVALS
# sub-intervals of each interval it touches: 5 nodes cannot follow a shorter rate pulse
RESOLVED_INTERVALS = 16
SUB_INTERVALS = 64


@dataclass
class KinState:
    """Pig state at a set of times (all arrays share the leading shape (M,)).

    s m chainage, sd m/s, sdd m/s^2; roll rad, roll_rate rad/s; azimuth, pitch rad (of the pipe
    axis, local ENU); lat, lon rad, h m; c_nb (M, 3, 3) base_link -> ENU; w_nb_b (M, 3) rad/s
    body rate relative to ENU in base_link; v_n (M, 3) m/s; a_n (M, 3) m/s^2 derivative of the
    ENU velocity components; w_ie_n, w_en_n (M, 3) rad/s; g_n (M, 3) m/s^2 normal gravity.
    """

    t: FloatArray
    s: FloatArray
    sd: FloatArray
    sdd: FloatArray
    roll: FloatArray
    roll_rate: FloatArray
    azimuth: FloatArray
    pitch: FloatArray
    lat: FloatArray
    lon: FloatArray
    h: FloatArray
    c_nb: FloatArray
    w_nb_b: FloatArray
    v_n: FloatArray
    a_n: FloatArray
    w_ie_n: FloatArray
    w_en_n: FloatArray
    g_n: FloatArray

    def quat_nb(self) -> FloatArray:
        """q_nb (M, 4) scalar-last, base_link -> ENU, non-negative scalar part."""
        return quat_from_angles(self.roll, self.pitch, self.azimuth)

    def omega_ib_b(self) -> FloatArray:
        """Ideal gyro signal omega_ib^b (M, 3), rad/s, in base_link."""
        w_in = self.w_ie_n + self.w_en_n
        return self.w_nb_b + np.einsum("mij,mi->mj", self.c_nb, w_in)

    def omega_eb_b(self) -> FloatArray:
        """Body rate relative to the Earth (and to the pipe), omega_eb^b (M, 3), rad/s."""
        return self.w_nb_b + np.einsum("mij,mi->mj", self.c_nb, self.w_en_n)

    def wall_speed(self, lever: FloatArray) -> FloatArray:
        """Speed (M,), m/s, of the wall point at ``lever`` (m, base_link) along the pipe: the
        chainage rate plus (omega_eb x lever)_x, as the odometer wheel there rolls."""
        w_eb = self.omega_eb_b()
        return self.sd + (w_eb[:, 1] * lever[2] - w_eb[:, 2] * lever[1])

    def specific_force_b(self) -> FloatArray:
        """Ideal accelerometer signal f^b (M, 3), m/s^2, in base_link."""
        f_n = self.a_n + np.cross(2.0 * self.w_ie_n + self.w_en_n, self.v_n) - self.g_n
        return np.einsum("mij,mi->mj", self.c_nb, f_n)


def quat_from_angles(roll: ArrayLike, pitch: ArrayLike, azimuth: ArrayLike) -> FloatArray:
    """q_nb (..., 4) scalar-last of C_nb = dcm_from_euler(roll, pitch, azimuth) (rad), in closed
    form (q_z(yaw) q_y(-pitch) q_x(roll), yaw = pi/2 - azimuth), non-negative scalar part."""
    roll = np.asarray(roll, dtype=np.float64)
    pitch = np.asarray(pitch, dtype=np.float64)
    yaw = 0.5 * np.pi - np.asarray(azimuth, dtype=np.float64)
    z = np.zeros(np.broadcast(roll, pitch, yaw).shape)
    qz = np.stack([z, z, z + np.sin(0.5 * yaw), z + np.cos(0.5 * yaw)], axis=-1)
    qy = np.stack([z, z + np.sin(-0.5 * pitch), z, z + np.cos(-0.5 * pitch)], axis=-1)
    qx = np.stack([z + np.sin(0.5 * roll), z, z, z + np.cos(0.5 * roll)], axis=-1)
    return quat_normalize(quat_mul(quat_mul(qz, qy), qx))


def evaluate(geometry: PipeGeometry, motion: PigMotion, t: ArrayLike) -> KinState:
    """The exact state at times t (s, 1-D, non-decreasing for speed)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    s, sd, sdd = motion.chainage(t)
    roll, roll_rate = motion.roll(t, s, sd)
    psi, th, kh, kv = geometry.direction(s)
    lat, lon, h = geometry.position(s)
    c_nb = dcm_from_euler(roll, th, psi)
    cpsi, spsi = np.cos(psi), np.sin(psi)
    cth, sth = np.cos(th), np.sin(th)
    u = np.stack([cth * spsi, cth * cpsi, sth], axis=-1)
    du = np.stack(
        [-sth * spsi * kv + cth * cpsi * kh, -sth * cpsi * kv - cth * spsi * kh, cth * kv],
        axis=-1,
    )
    v_n = sd[:, None] * u
    a_n = sdd[:, None] * u + (sd * sd)[:, None] * du
    # Body rate relative to ENU from the Euler rates of C = Rz(yaw) Ry(-pitch) Rx(roll).
    yaw_rate = -kh * sd
    pitch_rate = kv * sd
    cr, sr = np.cos(roll), np.sin(roll)
    w_nb_b = np.stack(
        [
            roll_rate + yaw_rate * sth,
            -pitch_rate * cr + yaw_rate * sr * cth,
            pitch_rate * sr + yaw_rate * cr * cth,
        ],
        axis=-1,
    )
    return KinState(
        t=t,
        s=s,
        sd=sd,
        sdd=sdd,
        roll=roll,
        roll_rate=roll_rate,
        azimuth=psi,
        pitch=th,
        lat=lat,
        lon=lon,
        h=h,
        c_nb=c_nb,
        w_nb_b=w_nb_b,
        v_n=v_n,
        a_n=a_n,
        w_ie_n=earth.earth_rate_n(lat),
        w_en_n=earth.transport_rate_n(lat, h, v_n),
        g_n=earth.gravity_n(lat, h),
    )


def lobatto_times(t_end: FloatArray, dt: float, t_start: float | None = None) -> FloatArray:
    """Quadrature times for the intervals ending at t_end[k] (s): each interval's start, three
    interior Lobatto nodes and its end, with ends shared. The first interval starts at
    ``t_start`` (default t_end[0] - dt), interval k > 0 at t_end[k - 1]; the interior nodes
    assume the nominal length dt. Shape (4 K + 1,), s."""
    t_end = np.asarray(t_end, dtype=np.float64)
    t0 = float(t_end[0] - dt) if t_start is None else float(t_start)
    starts = np.concatenate([[t0], t_end[:-1]])
    frac = 0.5 * (LOBATTO_X[1:-1] + 1.0)  # the three interior nodes
    nodes = np.empty((len(t_end), 4))
    nodes[:, :3] = starts[:, None] + dt * frac[None, :]
    nodes[:, 3] = t_end
    return np.concatenate([[t0], nodes.reshape(-1)])


def interval_means(values: FloatArray) -> FloatArray:
    """Means over the intervals of :func:`lobatto_times` of values sampled there.

    values: (4 K + 1, ...) -> (K, ...).
    """
    k = (values.shape[0] - 1) // 4
    out = 0.5 * LOBATTO_W[0] * values[0 : 4 * k : 4]
    for j in range(1, 5):
        out = out + 0.5 * LOBATTO_W[j] * values[j : 4 * k + 1 : 4][:k]
    return out


def short_feature_intervals(
    spans: FloatArray, s_bounds: FloatArray, resolved: int = RESOLVED_INTERVALS
) -> NDArray[np.int64]:
    """The sample intervals (k: from chainage s_bounds[k] to s_bounds[k + 1], m) that a
    feature of extent spans (N, 2) [start, end] m passes through while spanning fewer than
    ``resolved`` such intervals: there the Lobatto nodes cannot follow its rate pulse. (A
    0.2 deg vertical bend of radius 3 D is 5 mm of pipe, 2.5 ms at 2 m/s: the nodes of a
    200 Hz interval missed it whole, and the true attitude turned 3.9 mrad that no simulated
    gyro sample showed.) Sorted, unique."""
    s_bounds = np.asarray(s_bounds, dtype=np.float64)
    K = len(s_bounds) - 1
    if K < 1 or not len(spans):
        return np.zeros(0, dtype=np.int64)
    ds = np.diff(s_bounds)
    out: list[NDArray[np.int64]] = []
    lo = np.searchsorted(s_bounds, spans[:, 0], side="right") - 1
    hi = np.searchsorted(s_bounds, spans[:, 1], side="left")
    for (a, b), i, j in zip(spans, np.maximum(lo, 0), np.minimum(hi, K), strict=True):
        if j <= i:
            continue
        ks = np.arange(i, j)
        out.append(ks[(b - a) < resolved * ds[ks]])
    return np.unique(np.concatenate(out)) if out else np.zeros(0, dtype=np.int64)


def sub_interval_times(
    tn: FloatArray, ks: NDArray[np.int64], sub: int = SUB_INTERVALS
) -> FloatArray:
    """Lobatto times (:func:`lobatto_times`) of ``sub`` equal sub-intervals of each interval
    ks of the quadrature times tn (4 K + 1,), one after the other: (len(ks) * (4 sub + 1),)."""
    parts = []
    for k in ks:
        t0, t1 = tn[4 * k], tn[4 * k + 4]
        ends = t0 + (t1 - t0) * np.arange(1, sub + 1) / sub
        parts.append(lobatto_times(ends, (t1 - t0) / sub, t_start=t0))
    return np.concatenate(parts) if parts else np.zeros(0)


def sub_interval_means(values: FloatArray, count: int, sub: int = SUB_INTERVALS) -> FloatArray:
    """Means over each of ``count`` intervals of values sampled at :func:`sub_interval_times`:
    values (count * (4 sub + 1), ...) -> (count, ...)."""
    per = values.reshape(count, 4 * sub + 1, *values.shape[1:])
    return np.stack([interval_means(v).mean(axis=0) for v in per]) if count else values[:0]
