"""Error-state transition matrix and process noise over one filter epoch.

Built from the sums a mechanization block leaves (:class:`mechanization.BlockResult`), so that a
pig rolling at several rad/s inside one epoch still gets the exact bias couplings
(sum of C_nb dt over the samples), and then Phi = I + A + A^2 / 2 with A the integrated system
matrix. Error-state conventions: :mod:`pipe_nav_core.model.state`. Compiled kernels on the flat
state and the layout index array (:mod:`pipe_nav_core.model.state`), called by the engine's
compiled epoch (:mod:`pipe_nav_core.filter.epoch`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.sensors import G0, ImuSpec
from pipe_nav_core.model.state import (
    I_BORE,
    I_VEL,
    L_AM,
    L_ATT,
    L_BA,
    L_BG,
    L_BORE,
    L_DIR,
    L_GM,
    L_K,
    L_N,
    L_ODOQ,
    L_POS,
    L_VEL,
    SV_H,
    SV_LAT,
    c_nb_k,
    odometer_axis,
)

Array = NDArray[np.float64]
Index = NDArray[np.int64]


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
    """A = integral of F dt over the block (n, n), linearized about the flat state sv (layout
    L), from the block's sums (:class:`mechanization.BlockResult`, earth_sign -1 for reversed
    time).

    dv_f: the specific-force velocity increment (m/s, ENU) in the attitude-to-velocity
    coupling: the engine's first-estimate value (see
    :class:`pipe_nav_core.filter.navigator.Navigator`).
    at_rest: the pig is known to be stopped over the block; the couplings that multiply the
    true body rate and specific force (gyro and accelerometer error matrices) then use their
    exact values (the Earth rate and the gravity reaction (0, 0, g) m/s^2 ENU) instead of the
    noisy measured ones: with a consumer-grade IMU the measured values of a pig at rest are
    pure noise, and a Jacobian built from them, read against zero-velocity updates of 2 mm/s,
    makes the heading look observable at rest when it is not.
    heading_free: leave out the Earth rate's coupling of a heading error into the tilt (the
    engine's live filter, while its heading is still tens of degrees off and unanchored)."""
    n = L[L_N]
    A = np.zeros((n, n))
    a, p = L[L_ATT], L[L_POS]
    lat, h = sv[SV_LAT], sv[SV_H]
    g = earth._gravity(lat, h)
    w_ie = earth.earth_rate_k(lat, earth_sign)
    if at_rest:  # the exact rate and specific force of a pig at rest
        c = c_nb_k(sv)
        sum_c_w_dt = np.empty((3, 9))
        sum_c_f_dt = np.empty((3, 9))
        for j in range(3):
            w_b = c[0, j] * w_ie[0] + c[1, j] * w_ie[1] + c[2, j] * w_ie[2]
            f_b = c[2, j] * g
            for r in range(3):
                for i in range(3):
                    sum_c_w_dt[r, 3 * i + j] = c[r, i] * (w_b * T)
                    sum_c_f_dt[r, 3 * i + j] = c[r, i] * (f_b * T)
    bg, gm = L[L_BG], L[L_GM]
    A[a : a + 3, a : a + 3] = att.skew_k(w_in) * -T
    if heading_free:
        A[a, a + 2] = 0.0
        A[a + 1, a + 2] = 0.0
    A[a : a + 3, bg : bg + 3] = -sum_c_dt
    if gm >= 0:
        A[a : a + 3, gm : gm + 9] = -sum_c_w_dt
    v = L[L_VEL]
    if v >= 0:
        rm, rn = earth._radii(lat)
        A[a, v + 1] = 1.0 / (rm + h) * T
        A[a + 1, v] = -1.0 / (rn + h) * T
        A[a + 2, v] = -np.tan(lat) / (rn + h) * T
        w_en = earth.transport_rate_k(lat, h, sv[I_VEL], sv[I_VEL + 1])
        ba, am = L[L_BA], L[L_AM]
        A[v : v + 3, a : a + 3] = -att.skew_k(dv_f)
        A[v : v + 3, v : v + 3] = att.skew_k(2.0 * w_ie + w_en) * -T
        A[v : v + 3, ba : ba + 3] = -sum_c_dt
        if am >= 0:
            A[v : v + 3, am : am + 9] = -sum_c_f_dt
        for r in range(3):
            A[p + r, v + r] = T
        A[v + 2, p + 2] = 2.0 * g / (np.sqrt(rm * rn) + h) * T
    else:
        A[p : p + 3, a : a + 3] = -att.skew_k(dp)
        A[p : p + 3, L[L_K]] = dp_dk
        A[p : p + 3, L[L_BORE] : L[L_BORE] + 2] = dp_dbore
    return A


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
    section_wander: float,
) -> Array:
    """Process noise accumulated over the block (n, n) before propagation through it.

    imu: [gyro_arw, accel_vrw, gyro_bias_instability, gyro_bias_corr_time,
    accel_bias_instability, accel_bias_corr_time] (:func:`imu_noise`); scale_rw 1/sqrt(s);
    DR mode: dr_along_sigma and dr_lateral_sigma m/sqrt(m) of path, bend_sigma m of extra
    along-track noise for wall-versus-centreline differences in bends (zero when the wheel
    lever arm is known); odometer_resolution m per count: the fresh reading error at the epoch
    end is uniform over one count (variance resolution^2 / 12); section_wander rad/sqrt(m) of
    path: how far a straight section's direction may turn (NavConfig.straight_pipe_wander)."""
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
    fill(L[L_DIR], 2, section_wander**2 * path)
    if L[L_ODOQ] >= 0:
        Q[L[L_ODOQ] + 1, L[L_ODOQ] + 1] = odometer_resolution**2 / 12.0
    if L[L_VEL] < 0:
        u, _ = odometer_axis(sv[I_BORE : I_BORE + 2])
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


# Quantile of the chi-square distribution with 2 degrees of freedom at 95 %, halved: the
# second-order vertical term (bx^2 + by^2) / (2 g) of horizontal accelerometer biases with
# sigma s stays below TILT_SECOND_ORDER * s^2 / g in 95 % of turn-ons.
TILT_SECOND_ORDER = 3.0


def accel_bias_allowance(imu: ImuSpec) -> float:
    """The accelerometer bias instability (m/s^2) the filter models: the sensor's, plus in
    quadrature the second-order tilt term its linear error model leaves out.

    The static alignment levels the pig on the measured specific force, bias included, and
    takes the vertical bias from its magnitude, which holds (bx^2 + by^2) / (2 g) of the
    horizontal biases. A linear error model sees a tilt error and the horizontal bias that
    caused it as leaving the vertical untouched; when a sag or a roll later resolves them,
    that term turns into a vertical accelerometer error the filter would otherwise explain
    with wrong pitch and boresight corrections (sag104 seed 2: forward filter 63 % inside 3
    sigma without it, 100 % with it). Allowed for as bias instability of
    TILT_SECOND_ORDER * turn_on^2 / g."""
    second = TILT_SECOND_ORDER * imu.accel_turn_on_bias**2 / G0
    return float(np.hypot(imu.accel_bias_instability, second))


def imu_noise(imu: ImuSpec) -> Array:
    """The IMU noise densities process_noise_k takes, in its order (the accelerometer bias
    instability with :func:`accel_bias_allowance`)."""
    return np.array(
        [
            imu.gyro_arw,
            imu.accel_vrw,
            imu.gyro_bias_instability,
            imu.gyro_bias_corr_time,
            accel_bias_allowance(imu),
            imu.accel_bias_corr_time,
        ]
    )


@kernel
def discretize_k(A: Array, Q: Array, L: Index) -> tuple[Array, Array]:
    """Phi = I + A + A^2/2 and Qd = Q + (A Q + Q A^T)/2 + A Q A^T / 3.

    Only the leading rows of A (the attitude, velocity and position errors) are nonzero, and
    sparse: the products are taken over its nonzeros alone (the same sums). With a layout
    that has odometer reading errors, their rows become the epoch shift (start <- end, end <-
    fresh draw whose variance Q holds); A never couples them."""
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
