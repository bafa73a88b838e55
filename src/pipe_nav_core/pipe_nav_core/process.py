"""Error-state transition matrix and process noise over one filter epoch.

Built from the sums a mechanization block leaves (:class:`mechanization.BlockResult`), so that a
pig rolling at several rad/s inside one epoch still gets the exact bias couplings
(sum of C_nb dt over the samples), and then Phi = I + A + A^2 / 2 with A the integrated system
matrix. Error-state conventions: :mod:`pipe_nav_core.state`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from . import earth
from .mechanization import BlockResult
from .sensors import ImuSpec
from .state import Layout, NavState, odometer_axis, skew3

Array = NDArray[np.float64]


def integrated_system_matrix(
    s: NavState,
    blk: BlockResult,
    layout: Layout,
    earth_sign: float = 1.0,
    *,
    at_rest: bool = False,
    dv_f: Array | None = None,
    heading_free: bool = False,
) -> Array:
    """A = integral of F dt over the block (n, n), linearized about the nominal state s.

    at_rest: the pig is known to be stopped over the block; the couplings that multiply the
    true specific force and the true body rate then use their exact values (gravity reaction
    (0, 0, g) m/s^2 ENU and the Earth rate) instead of the noisy measured ones. With a
    consumer-grade IMU the measured horizontal specific force of a pig at rest is pure noise
    (about 1e-3 m/s per 0.1 s epoch), and a Jacobian built from it, read against zero-velocity
    updates of 2 mm/s, makes the heading look observable at rest when it is not.
    dv_f: the specific-force velocity increment (m/s, ENU) to use in the attitude-to-velocity
    coupling instead of the block's own (the engine's first-estimate Jacobian, see
    :meth:`pipe_nav_core.engine.Navigator`); overrides the at_rest value.
    heading_free: leave out the Earth rate's coupling of a heading error into the tilt (the
    engine's live filter, while its heading is still tens of degrees off and unanchored).
    """
    n = layout.n
    A = np.zeros((n, n))
    T = blk.T
    a, p = layout.att, layout.pos
    sum_c_w_dt, sum_c_f_dt = blk.sum_c_w_dt, blk.sum_c_f_dt
    g = earth.gravity(s.lat, s.h)
    w_ie = earth_sign * earth.earth_rate_n(s.lat)
    if dv_f is None:
        dv_f = np.array([0.0, 0.0, g * T]) if at_rest else blk.dv_f
    if at_rest:
        c = s.c_nb
        w_b = c.T @ w_ie
        sum_c_w_dt = np.einsum("ai,j->aij", c, w_b * T).reshape(3, 9)
        f_b = c.T @ np.array([0.0, 0.0, g])
        sum_c_f_dt = np.einsum("ai,j->aij", c, f_b * T).reshape(3, 9)
    A[a, a] = -skew3(blk.w_in) * T
    if heading_free:
        A[a.start : a.start + 2, a.start + 2] = 0.0
    A[a, layout.bg] = -blk.sum_c_dt
    if layout.gm is not None:
        A[a, layout.gm] = -sum_c_w_dt
    if layout.vel is not None:
        v = layout.vel
        rm, rn = earth.radii(s.lat)
        m_v = np.array(
            [
                [0.0, -1.0 / (rm + s.h), 0.0],
                [1.0 / (rn + s.h), 0.0, 0.0],
                [math.tan(s.lat) / (rn + s.h), 0.0, 0.0],
            ]
        )
        w_en = earth.transport_rate_n(s.lat, s.h, s.vel_n)
        A[a, v] = -m_v * T
        A[v, a] = -skew3(dv_f)
        A[v, v] = -skew3(2.0 * w_ie + w_en) * T
        A[v, layout.ba] = -blk.sum_c_dt
        if layout.am is not None:
            A[v, layout.am] = -sum_c_f_dt
        A[v.start + 2, p.start + 2] = 2.0 * g / (math.sqrt(rm * rn) + s.h) * T
        A[p, v] = np.eye(3) * T
    else:
        A[p, a] = -skew3(blk.dp)
        A[p, layout.k] = blk.dp_dk[:, None]
        A[p, layout.bore] = blk.dp_dbore
    return A


def continuous_noise(
    s: NavState,
    blk: BlockResult,
    layout: Layout,
    imu: ImuSpec,
    *,
    scale_rw: float,
    dr_along_sigma: float,
    dr_lateral_sigma: float,
    bend_sigma: float,
    odometer_resolution: float = 0.0,
) -> Array:
    """Process noise accumulated over the block (n, n) before propagation through the block.

    bend_sigma: m, extra along-track distance noise in DR mode for wall-versus-centreline
    differences in bends (zero when the wheel lever arm is known and compensated).
    odometer_resolution: m per count; the fresh reading error at the epoch end is uniform over
    one count (variance resolution^2 / 12).
    """
    T = blk.T
    q = np.zeros(layout.n)
    q[layout.att] = imu.gyro_arw**2 * T
    if layout.vel is not None:
        q[layout.vel] = imu.accel_vrw**2 * T
    q[layout.bg] = 2.0 * imu.gyro_bias_instability**2 / imu.gyro_bias_corr_time * T
    q[layout.ba] = 2.0 * imu.accel_bias_instability**2 / imu.accel_bias_corr_time * T
    q[layout.k] = scale_rw**2 * T
    q[layout.bore] = 1e-8**2 * T
    if layout.gm is not None:
        q[layout.gm] = 1e-9**2 * T
    if layout.am is not None:
        q[layout.am] = 1e-9**2 * T
    if layout.odoq is not None:
        q[layout.odoq.start + 1] = odometer_resolution**2 / 12.0
    Q = np.diag(q)
    if layout.vel is None:
        u, _ = odometer_axis(s.bore)
        c_mean = blk.sum_c_dt / max(T, 1e-12)
        u_n = c_mean @ u
        u_n /= np.linalg.norm(u_n)
        along = np.outer(u_n, u_n)
        path = blk.path
        Q[layout.pos, layout.pos] = (
            dr_along_sigma**2 * path + bend_sigma**2
        ) * along + dr_lateral_sigma**2 * path * (np.eye(3) - along)
    return Q


def discretize(A: Array, Q: Array, layout: Layout | None = None) -> tuple[Array, Array]:
    """Phi = I + A + A^2/2 and Qd = Q + (A Q + Q A^T)/2 + A Q A^T / 3.

    Only the leading rows of A (the attitude, velocity and position errors) are nonzero; the
    products are taken over those rows alone (the same sums, without the zero terms).
    With a layout that has odometer reading errors, their rows become the epoch shift
    (start <- end, end <- fresh draw whose variance Q holds); A never couples them.
    """
    n = A.shape[0]
    nonzero = np.flatnonzero(A.any(axis=1))
    r = int(nonzero[-1]) + 1 if len(nonzero) else 0  # A[r:] == 0
    Ar = A[:r]
    phi = np.eye(n) + A
    phi[:r] += 0.5 * (Ar[:, :r] @ Ar)
    AQ = Ar @ Q  # (r, n): the rows of A Q below r are zero
    qd = Q.copy()
    qd[:r, :r] += 0.5 * (AQ[:, :r] + AQ[:, :r].T) + (AQ @ Ar.T) / 3.0
    qd[:r, r:] += 0.5 * AQ[:, r:]
    qd[r:, :r] += 0.5 * AQ[:, r:].T
    if layout is not None and layout.odoq is not None:
        i = layout.odoq.start
        phi[i : i + 2, :] = 0.0
        phi[i, i + 1] = 1.0
    return phi, 0.5 * (qd + qd.T)
