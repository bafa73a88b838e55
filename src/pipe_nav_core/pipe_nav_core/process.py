"""Error-state transition matrix and process noise over one filter epoch.

Built from the sums a mechanization block leaves (:class:`mechanization.BlockResult`), so that a
pig rolling at several rad/s inside one epoch still gets the exact bias couplings
(sum of C_nb dt over the samples), and then Phi = I + A + A^2 / 2 with A the integrated system
matrix. Error-state conventions: :mod:`pipe_nav_core.state`. The ``*_k`` kernels are compiled
(flat state, layout index array, see :mod:`pipe_nav_core.state`) and shared by the engine's
compiled epoch; the functions without the suffix are their NavState / BlockResult front ends.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import attitude as att
from . import earth
from .jit import kernel
from .mechanization import BlockResult
from .sensors import ImuSpec
from .state import (
    I_Q,
    I_VEL,
    L_AM,
    L_ATT,
    L_BA,
    L_BG,
    L_BORE,
    L_GM,
    L_K,
    L_N,
    L_ODOQ,
    L_POS,
    L_VEL,
    SV_H,
    SV_LAT,
    Layout,
    NavState,
    odometer_axis,
)

Array = NDArray[np.float64]
Index = NDArray[np.int64]


@kernel
def _skew_into(A: Array, r: int, c: int, v0: float, v1: float, v2: float, scale: float) -> None:
    """A[r:r+3, c:c+3] = scale * [v x]."""
    A[r, c + 1] = -v2 * scale
    A[r, c + 2] = v1 * scale
    A[r + 1, c] = v2 * scale
    A[r + 1, c + 2] = -v0 * scale
    A[r + 2, c] = -v1 * scale
    A[r + 2, c + 1] = v0 * scale


@kernel
def system_matrix_k(
    sv: Array,
    L: Index,
    T: float,
    w_in: Array,
    sum_c_dt: Array,
    sum_c_w_dt: Array,
    sum_c_f_dt: Array,
    dv_f: Array,
    dp: Array,
    dp_dk: Array,
    dp_dbore: Array,
    earth_sign: float,
    at_rest: bool,
    heading_free: bool,
) -> Array:
    """A = integral of F dt over the block (n, n) about the flat state sv (see
    :func:`integrated_system_matrix`; dv_f is the specific-force increment to use, m/s ENU)."""
    n = L[L_N]
    A = np.zeros((n, n))
    a, p = L[L_ATT], L[L_POS]
    lat, h = sv[SV_LAT], sv[SV_H]
    g = earth._gravity(lat, h)
    w_ie = (
        0.0,
        earth_sign * earth.OMEGA_IE * np.cos(lat),
        earth_sign * earth.OMEGA_IE * np.sin(lat),
    )
    if at_rest:  # the exact rate and specific force of a pig at rest
        c = np.empty((3, 3))
        att.dcm_into((sv[I_Q], sv[I_Q + 1], sv[I_Q + 2], sv[I_Q + 3]), c)
        sum_c_w_dt = np.empty((3, 9))
        sum_c_f_dt = np.empty((3, 9))
        for j in range(3):
            w_b = c[0, j] * w_ie[0] + c[1, j] * w_ie[1] + c[2, j] * w_ie[2]
            f_b = c[2, j] * g
            for r in range(3):
                for i in range(3):
                    sum_c_w_dt[r, 3 * i + j] = c[r, i] * (w_b * T)
                    sum_c_f_dt[r, 3 * i + j] = c[r, i] * (f_b * T)
    _skew_into(A, a, a, w_in[0], w_in[1], w_in[2], -T)
    if heading_free:
        A[a, a + 2] = 0.0
        A[a + 1, a + 2] = 0.0
    for r in range(3):
        for i in range(3):
            A[a + r, L[L_BG] + i] = -sum_c_dt[r, i]
        if L[L_GM] >= 0:
            for i in range(9):
                A[a + r, L[L_GM] + i] = -sum_c_w_dt[r, i]
    v = L[L_VEL]
    if v >= 0:
        rm, rn = earth._radii(lat)
        ve, vn = sv[I_VEL], sv[I_VEL + 1]
        A[a, v + 1] = 1.0 / (rm + h) * T
        A[a + 1, v] = -1.0 / (rn + h) * T
        A[a + 2, v] = -np.tan(lat) / (rn + h) * T
        w_en = (-vn / (rm + h), ve / (rn + h), ve * np.tan(lat) / (rn + h))
        _skew_into(A, v, a, dv_f[0], dv_f[1], dv_f[2], -1.0)
        _skew_into(
            A,
            v,
            v,
            2.0 * w_ie[0] + w_en[0],
            2.0 * w_ie[1] + w_en[1],
            2.0 * w_ie[2] + w_en[2],
            -T,
        )
        for r in range(3):
            for i in range(3):
                A[v + r, L[L_BA] + i] = -sum_c_dt[r, i]
            if L[L_AM] >= 0:
                for i in range(9):
                    A[v + r, L[L_AM] + i] = -sum_c_f_dt[r, i]
            A[p + r, v + r] = T
        A[v + 2, p + 2] = 2.0 * g / (np.sqrt(rm * rn) + h) * T
    else:
        _skew_into(A, p, a, dp[0], dp[1], dp[2], -1.0)
        for r in range(3):
            A[p + r, L[L_K]] = dp_dk[r]
            A[p + r, L[L_BORE]] = dp_dbore[r, 0]
            A[p + r, L[L_BORE] + 1] = dp_dbore[r, 1]
    return A


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
    if dv_f is None:
        g = float(earth.gravity(s.lat, s.h))
        dv_f = np.array([0.0, 0.0, g * blk.T]) if at_rest else blk.dv_f
    return system_matrix_k(
        s.vector(),
        layout.index,
        blk.T,
        blk.w_in,
        blk.sum_c_dt,
        blk.sum_c_w_dt,
        blk.sum_c_f_dt,
        np.asarray(dv_f, dtype=np.float64),
        blk.dp,
        blk.dp_dk,
        blk.dp_dbore,
        float(earth_sign),
        bool(at_rest),
        bool(heading_free),
    )


@kernel
def process_noise_k(
    sv: Array,
    L: Index,
    T: float,
    sum_c_dt: Array,
    path: float,
    imu: Array,
    scale_rw: float,
    dr_along_sigma: float,
    dr_lateral_sigma: float,
    bend_sigma: float,
    odometer_resolution: float,
) -> Array:
    """Process noise over the block (n, n) (see :func:`continuous_noise`); imu = [gyro_arw,
    accel_vrw, gyro_bias_instability, gyro_bias_corr_time, accel_bias_instability,
    accel_bias_corr_time] (:func:`imu_noise`)."""
    n = L[L_N]
    Q = np.zeros((n, n))

    def fill(block: int, size: int, value: float) -> None:
        if block >= 0:
            for i in range(size):
                Q[block + i, block + i] = value

    fill(L[L_ATT], 3, imu[0] ** 2 * T)
    fill(L[L_VEL], 3, imu[1] ** 2 * T)
    fill(L[L_BG], 3, 2.0 * imu[2] ** 2 / imu[3] * T)
    fill(L[L_BA], 3, 2.0 * imu[4] ** 2 / imu[5] * T)
    fill(L[L_K], 1, scale_rw**2 * T)
    fill(L[L_BORE], 2, 1e-8**2 * T)
    fill(L[L_GM], 9, 1e-9**2 * T)
    fill(L[L_AM], 9, 1e-9**2 * T)
    if L[L_ODOQ] >= 0:
        Q[L[L_ODOQ] + 1, L[L_ODOQ] + 1] = odometer_resolution**2 / 12.0
    if L[L_VEL] < 0:
        u, _ = odometer_axis(sv[18:20])
        u_n = np.zeros(3)
        for r in range(3):
            for i in range(3):
                u_n[r] += sum_c_dt[r, i] / max(T, 1e-12) * u[i]
        u_n /= np.sqrt(u_n[0] ** 2 + u_n[1] ** 2 + u_n[2] ** 2)
        along = dr_along_sigma**2 * path + bend_sigma**2
        lateral = dr_lateral_sigma**2 * path
        p = L[L_POS]
        for r in range(3):
            for c in range(3):
                uu = u_n[r] * u_n[c]
                Q[p + r, p + c] = along * uu + lateral * ((1.0 if r == c else 0.0) - uu)
    return Q


def imu_noise(imu: ImuSpec) -> Array:
    """The IMU noise densities process_noise_k takes, in its order."""
    return np.array(
        [
            imu.gyro_arw,
            imu.accel_vrw,
            imu.gyro_bias_instability,
            imu.gyro_bias_corr_time,
            imu.accel_bias_instability,
            imu.accel_bias_corr_time,
        ]
    )


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
    return process_noise_k(
        s.vector(),
        layout.index,
        blk.T,
        blk.sum_c_dt,
        float(blk.path),
        imu_noise(imu),
        float(scale_rw),
        float(dr_along_sigma),
        float(dr_lateral_sigma),
        float(bend_sigma),
        float(odometer_resolution),
    )


@kernel
def discretize_k(A: Array, Q: Array, L: Index) -> tuple[Array, Array]:
    """Phi = I + A + A^2/2 and Qd = Q + (A Q + Q A^T)/2 + A Q A^T / 3 (see :func:`discretize`)."""
    n = A.shape[0]
    r = 0  # A[r:] == 0
    for i in range(n):
        for j in range(n):
            if A[i, j] != 0.0:
                r = i + 1
                break
    # products over the nonzeros of A's leading rows (A is sparse; zeros add nothing)
    phi = np.eye(n) + A
    AA = np.zeros((r, n))  # A[:r, :r] A[:r]
    AQ = np.zeros((r, n))  # A[:r] Q
    for i in range(r):
        for k in range(n):
            a = A[i, k]
            if a != 0.0:
                if k < r:
                    for j in range(n):
                        AA[i, j] += a * A[k, j]
                for j in range(n):
                    AQ[i, j] += a * Q[k, j]
    AQA = np.zeros((r, r))  # A Q A^T
    for i in range(r):
        for k in range(r):
            acc = 0.0
            for j in range(n):
                acc += AQ[i, j] * A[k, j]
            AQA[i, k] = acc
    qd = Q.copy()
    for i in range(r):
        for j in range(n):
            phi[i, j] += 0.5 * AA[i, j]
        for j in range(r):
            qd[i, j] += 0.5 * (AQ[i, j] + AQ[j, i]) + AQA[i, j] / 3.0
        for j in range(r, n):
            qd[i, j] += 0.5 * AQ[i, j]
            qd[j, i] += 0.5 * AQ[i, j]
    i = L[L_ODOQ]
    if i >= 0:
        phi[i : i + 2, :] = 0.0
        phi[i, i + 1] = 1.0
    return phi, 0.5 * (qd + qd.T)


def discretize(A: Array, Q: Array, layout: Layout | None = None) -> tuple[Array, Array]:
    """Phi = I + A + A^2/2 and Qd = Q + (A Q + Q A^T)/2 + A Q A^T / 3.

    Only the leading rows of A (the attitude, velocity and position errors) are nonzero; the
    products are taken over those rows alone (the same sums, without the zero terms).
    With a layout that has odometer reading errors, their rows become the epoch shift
    (start <- end, end <- fresh draw whose variance Q holds); A never couples them.
    """
    L = layout.index if layout is not None else np.array([-1] * 10 + [A.shape[0]], np.int64)
    return discretize_k(np.ascontiguousarray(A, float), np.ascontiguousarray(Q, float), L)
