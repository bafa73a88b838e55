"""The filter epoch, compiled: mechanize the block of IMU samples, propagate the covariance,
apply the gated updates, inject the correction, write what the smoothers need.

:class:`pipe_nav_core.filter.navigator.Navigator` decides where epochs end, prepares the per-epoch
inputs
(odometer coverage and distance, encoder resolution, excluded slips, magnetometer sample) for a
batch of epochs, and calls :func:`run_epochs` once per batch; the rare events (alignment, the
heading re-anchoring and covariance recovery at a marker passage) stay in Python between
:func:`run_epochs` with ``stop`` (prediction only) and with ``resume`` (updates only). Every
model is the shared one (:mod:`process`, :mod:`measurements`, :mod:`kalman`, :mod:`state`).

Arrays and indices (all float64 unless said):
- :class:`Filter`: the filter's nominal state, mean error, covariance and memory, updated in
  place;
- ``prm`` (P_SIZE,) settings (:func:`parameters`); ``L`` the layout (Layout.index);
- ``ref`` (K, SV_SIZE) the reference trajectory (empty without one) and ``k0`` the epoch number
  of the batch's first epoch;
- :class:`Inputs`: the batch's IMU samples and per-epoch odometer and magnetometer data;
- :class:`EpochOutputs` (a :class:`Batch`'s arrays): per epoch, per sample (lat, lon, h, q_nb,
  odometer reading) and the update statistics.

About 500 lines, one module on purpose: the compiled epoch loop, its array records and their
index constants are read together, and numba compiles the loop with every function it calls
(a split would only move the constants away from the loop that reads them).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.kalman import chi2_threshold, predict_k
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements import (
    gravity_tilt,
    magnetic_heading,
    marker,
    odometer,
    zero_rate,
    zero_velocity,
)
from pipe_nav_core.model.measurements.context import (
    C_EPOCHS,
    COUNTERS,
    KINDS,
    P_CHI2,
    P_DR_ALONG,
    P_DR_LATERAL,
    P_EARTH_SIGN,
    P_IMU,
    P_LEVER,
    P_LEVER_KNOWN,
    P_MAG_DECL,
    P_MAG_DIP,
    P_MAG_DIP_GATE,
    P_MAG_NORM_GATE,
    P_MAG_ON,
    P_MAG_REF,
    P_MAG_REF_OK,
    P_MAG_SIGMA,
    P_MARKER_TIME,
    P_NHC_SIGMA,
    P_ODO_SIGMA,
    P_PIPE_D,
    P_SCALE_RW,
    P_SIZE,
    P_STOP_GYRO,
    P_STOP_SPEED,
    P_TILT_GATE,
    P_TILT_ON,
    P_TILT_SIGMA,
    P_ZARU,
    P_ZUPT,
    Context,
)
from pipe_nav_core.model.mechanization import dr_step_k, ins_step_k
from pipe_nav_core.model.process import discretize_k, imu_noise, process_noise_k, system_matrix_k
from pipe_nav_core.model.sensors import ImuSpec
from pipe_nav_core.model.state import (
    I_BG,
    I_VEL,
    L_N,
    L_VEL,
    SV_DIST,
    SV_K,
    SV_SIZE,
    SV_T,
    difference_k,
    inject_k,
)

Array = NDArray[np.float64]
Index = NDArray[np.int64]

# the filter's memory besides sv, x, P, carry (dyn)
D_PREV_SPEED, D_HAS_PREV_VEL, D_PREV_VEL, D_S_START, D_FREE, D_V_JAC = 0, 1, 2, 5, 6, 7
D_SIZE = 10

# the prediction's results the updates use (ws)
W_T, W_SPEED, W_STOPPED, W_HAS_ODO, W_EXCLUDED, W_LEVER_RATE, W_W_YZ = 0, 1, 2, 3, 4, 5, 6
W_I0, W_I1, W_MAG_I = 7, 8, 9
W_GYRO, W_OMEGA, W_MVB, W_FMN, W_DP, W_VJAC = 10, 13, 16, 19, 22, 25
W_SIZE = 28
S_MECH, S_LIN = 0, 1  # rows of ws_sv: the mechanized state, the updates' linearization point


def parameters(
    config: NavConfig,
    imu: ImuSpec,
    lever_arm: Array,
    earth_sign: float,
    mag_ref: tuple[float, float] | None,
) -> Array:
    """The settings array of the kernels."""
    c = config
    p = np.zeros(P_SIZE)
    p[P_EARTH_SIGN] = earth_sign
    p[P_PIPE_D] = c.pipe_diameter
    p[P_LEVER : P_LEVER + 3] = lever_arm
    p[P_LEVER_KNOWN] = float(np.any(lever_arm))
    p[P_STOP_SPEED], p[P_STOP_GYRO] = c.stop_speed_threshold, c.stop_gyro_threshold
    p[P_ODO_SIGMA], p[P_NHC_SIGMA] = c.odometer_speed_sigma, c.nhc_sigma
    p[P_ZUPT], p[P_ZARU] = c.zupt_sigma, c.zaru_sigma
    p[P_TILT_ON], p[P_TILT_GATE], p[P_TILT_SIGMA] = c.tilt_enabled(), c.tilt_gate, c.tilt_sigma
    p[P_MAG_ON], p[P_MAG_NORM_GATE] = c.mag_update, c.mag_magnitude_gate
    p[P_MAG_DIP_GATE], p[P_MAG_DECL] = c.mag_dip_gate, c.mag_declination
    p[P_MAG_SIGMA] = c.mag_heading_sigma
    if mag_ref is not None:
        p[P_MAG_REF], p[P_MAG_DIP], p[P_MAG_REF_OK] = mag_ref[0], mag_ref[1], 1.0
    p[P_SCALE_RW], p[P_DR_ALONG] = c.odometer_scale_rw, c.odometer_distance_sigma
    p[P_DR_LATERAL], p[P_MARKER_TIME] = c.dr_lateral_sigma, c.marker_time_sigma
    for m in (1, 2, 3):
        p[P_CHI2 + m - 1] = chi2_threshold(c.gate_probability, m)
    p[P_IMU : P_IMU + 6] = imu_noise(imu)
    return p


class Filter(NamedTuple):
    """The filter's memory, updated in place: nominal state ``sv`` (SV_SIZE,), mean error ``x``
    (n,), covariance ``P`` (n, n), the previous block's last increments ``carry`` (6,) and the
    rest ``dyn`` (D_SIZE,)."""

    sv: Array
    x: Array
    P: Array
    carry: Array
    dyn: Array


class Inputs(NamedTuple):
    """A batch's data: IMU samples (base_link; s, rad/s, m/s^2) from just after the state's
    time, each epoch's last sample ``ends``, the odometer reading at every sample ``s_odo``
    (m); per epoch ``has_odo``, ``excluded`` (slip), encoder ``resolution`` (m) and
    magnetometer sample ``mag_i`` (-1 none) into ``mag_t`` (s) / ``mag_f`` (T, base_link)."""

    imu_t: Array
    imu_g: Array
    imu_a: Array
    ends: Index
    s_odo: Array
    has_odo: NDArray[np.bool_]
    excluded: NDArray[np.bool_]
    resolution: Array
    mag_i: Index
    mag_t: Array
    mag_f: Array


class EpochOutputs(NamedTuple):
    """:class:`Batch`'s arrays as the compiled epoch writes them (see Batch)."""

    sv: Array
    x_upd: Array
    dx: Array
    end_offset: Array
    P_pred: Array
    P_upd: Array
    phi: Array
    stopped: NDArray[np.bool_]
    omega: Array
    lat: Array
    lon: Array
    h: Array
    q: Array
    s_odo: Array
    marker_res: Array
    counts: Index
    acc: Index
    rej: Index
    nis: Array
    dof: Index
    ws: Array
    ws_sv: Array
    ws_x: Array
    ws_m: Array


class Batch:
    """Output buffers of :func:`run_epochs` for up to ``size`` epochs and ``samples`` IMU
    samples: per epoch the estimate ``sv`` (after the update), ``x_upd`` (the filter's mean
    error after the updates), ``dx`` (what the updates moved, the RTS smoother's
    correction), ``end_offset``, ``P_pred``, ``P_upd``, ``phi``, ``stopped``, ``omega``
    (rad/s base_link); per sample ``lat``, ``lon`` (rad), ``h`` (m), ``q`` and the odometer
    reading ``s_odo`` (m); marker residuals (ENU m) per marker of the call; counters and
    update statistics (``acc``, ``rej``, ``nis``, ``dof`` per kind of KINDS)."""

    def __init__(self, size: int, samples: int, n: int) -> None:
        self.sv = np.zeros((size, SV_SIZE))
        self.x_upd = np.zeros((size, n))
        self.dx = np.zeros((size, n))
        self.end_offset = np.zeros((size, n))
        self.P_pred = np.zeros((size, n, n))
        self.P_upd = np.zeros((size, n, n))
        self.phi = np.zeros((size, n, n))
        self.stopped = np.zeros(size, dtype=np.bool_)
        self.omega = np.zeros((size, 3))
        self.lat = np.zeros(samples)
        self.lon = np.zeros(samples)
        self.h = np.zeros(samples)
        self.q = np.zeros((samples, 4))
        self.s_odo = np.zeros(samples)
        self.marker_res = np.zeros((0, 3))  # set per call with markers
        self.counts = np.zeros(len(COUNTERS), dtype=np.int64)
        self.acc = np.zeros(len(KINDS), dtype=np.int64)
        self.rej = np.zeros(len(KINDS), dtype=np.int64)
        self.nis = np.zeros(len(KINDS))
        self.dof = np.zeros(len(KINDS), dtype=np.int64)
        self.ws = np.zeros(W_SIZE)
        self.ws_sv = np.zeros((2, SV_SIZE))
        self.ws_x = np.zeros(n)
        self.ws_m = np.zeros((3, 12))

    def reset(self) -> None:
        """Zero the counters and statistics (before reusing the buffers)."""
        for a in (self.counts, self.acc, self.rej, self.nis, self.dof):
            a[:] = 0

    def buffers(self) -> EpochOutputs:
        """The arrays, as run_epochs takes them."""
        return EpochOutputs(*(getattr(self, name) for name in EpochOutputs._fields))


@kernel
def _predict(
    e: int,
    k_ep: int,
    f: Filter,
    L: Index,
    prm: Array,
    ref: Array,
    inp: Inputs,
    out: EpochOutputs,
) -> None:
    """Epoch e of the batch up to the prediction: mechanization, stop detection, transition,
    process noise, covariance propagation (Navigator's epoch, first half)."""
    sv, x, P, carry, dyn = f
    has_ref = ref.shape[0] > 0
    s0 = ref[k_ep - 1] if has_ref else sv.copy()
    i0 = inp.ends[e - 1] + 1 if e > 0 else 0
    i1 = inp.ends[e] + 1
    t = inp.imu_t[i0:i1]
    g = inp.imu_g[i0:i1]
    odo_ok = inp.has_odo[e]
    s_start = dyn[D_S_START]
    for i in range(i0, i1):
        out.s_odo[i] = inp.s_odo[i] if odo_ok else s_start
    ds = np.empty(i1 - i0)
    prev = s_start
    for i in range(i1 - i0):
        ds[i] = out.s_odo[i0 + i] - prev
        prev = out.s_odo[i0 + i]
    ins = L[L_VEL] >= 0
    earth_sign = prm[P_EARTH_SIGN]
    if ins:
        step = ins_step_k(s0, t, g, inp.imu_a[i0:i1], carry, earth_sign)
    else:
        step = dr_step_k(
            s0, t, g, inp.imu_a[i0:i1], ds, carry, prm[P_LEVER : P_LEVER + 3], earth_sign
        )
    s1, T, path = step.state, step.T, step.path
    sum_c_dt, sum_c_w_dt, sum_c_f_dt = step.sum_c_dt, step.sum_c_w_dt, step.sum_c_f_dt
    dv_f, dp, dp_dk, dp_dbore = step.dv_f, step.dp, step.dp_dk, step.dp_dbore
    omega_b, f_mean_n, mean_vel_b, w_in = step.omega_b, step.f_mean_n, step.mean_vel_b, step.w_in
    carry[:] = step.carry
    out.lat[i0:i1] = step.lat
    out.lon[i0:i1] = step.lon
    out.h[i0:i1] = step.h
    out.q[i0:i1] = step.q_nb
    speed = ds.sum() / T
    w_yz = np.hypot(omega_b[1], omega_b[2])
    lever_known = prm[P_LEVER_KNOWN] != 0.0
    bend_sigma = 0.0 if lever_known else 0.5 * prm[P_PIPE_D] * w_yz * T
    # time-weighted mean gyro reading, rad/s
    gyro_mean = np.zeros(3)
    w_sum = 0.0
    prev_t = s0[SV_T]
    for i in range(i1 - i0):
        w = t[i] - prev_t
        prev_t = t[i]
        w_sum += w
        for a in range(3):
            gyro_mean[a] += g[i, a] * w
    gyro_mean /= w_sum
    dg = gyro_mean - s1[I_BG : I_BG + 3]
    thr = prm[P_STOP_SPEED]
    stopped = (
        odo_ok
        and abs(speed) < thr
        and abs(dyn[D_PREV_SPEED]) < thr
        and np.sqrt(dg[0] ** 2 + dg[1] ** 2 + dg[2] ** 2) < prm[P_STOP_GYRO]
    )
    # the linearization point at the block end and the first-estimate Jacobian velocity
    s_lin = ref[k_ep] if has_ref else s1
    v_jac = np.zeros(3) if stopped else s_lin[I_VEL : I_VEL + 3].copy()
    if ins:
        dv_f = (
            dv_f
            + (v_jac - s1[I_VEL : I_VEL + 3])
            - (dyn[D_V_JAC : D_V_JAC + 3] - s0[I_VEL : I_VEL + 3])
        )
    A = system_matrix_k(
        s0,
        L,
        T,
        w_in,
        sum_c_dt,
        sum_c_w_dt,
        sum_c_f_dt,
        dv_f,
        dp,
        dp_dk,
        dp_dbore,
        earth_sign,
        stopped,
        dyn[D_FREE] != 0.0,
    )
    Q = process_noise_k(
        s0,
        L,
        T,
        sum_c_dt,
        path,
        prm[P_IMU : P_IMU + 6],
        prm[P_SCALE_RW],
        prm[P_DR_ALONG],
        prm[P_DR_LATERAL],
        bend_sigma,
        inp.resolution[e],
    )
    phi, qd = discretize_k(A, Q, L)
    offset = difference_k(s1, s_lin, L) if has_ref else np.zeros(L[L_N])
    predict_k(x, P, phi, qd, offset)
    s1[SV_DIST] = s0[SV_DIST] + (1.0 + s0[SV_K]) * ds.sum()
    out.P_pred[e] = P
    out.phi[e] = phi
    out.ws_x[:] = x
    out.ws_sv[S_MECH] = s1
    out.ws_sv[S_LIN] = s_lin
    out.ws[W_T], out.ws[W_SPEED], out.ws[W_STOPPED] = T, speed, stopped
    out.ws[W_HAS_ODO], out.ws[W_EXCLUDED], out.ws[W_W_YZ] = odo_ok, inp.excluded[e], w_yz
    lever = prm[P_LEVER : P_LEVER + 3]
    out.ws[W_LEVER_RATE] = omega_b[1] * lever[2] - omega_b[2] * lever[1]  # (omega x d)_x
    out.ws[W_I0], out.ws[W_I1], out.ws[W_MAG_I] = i0, i1, inp.mag_i[e]
    out.ws[W_GYRO : W_GYRO + 3] = gyro_mean
    out.ws[W_OMEGA : W_OMEGA + 3] = omega_b
    out.ws[W_MVB : W_MVB + 3] = mean_vel_b
    out.ws[W_FMN : W_FMN + 3] = f_mean_n
    out.ws[W_DP : W_DP + 3] = dp
    out.ws[W_VJAC : W_VJAC + 3] = v_jac
    out.ws_m[:, :3] = sum_c_dt  # for the tilt update: C_mean and the accelerometer coupling
    out.ws_m[:, 3:] = sum_c_f_dt


def context(
    ws: Array,
    ws_sv: Array,
    ws_m: Array,
    dyn: Array,
    L: Index,
    prm: Array,
    imu_t: Array,
    q: Array,
    mag_t: Array,
    mag_f: Array,
    markers: Array,
) -> Context:
    """The measurements' context of the epoch whose prediction left ws, ws_sv, ws_m (a
    Batch's, :func:`_predict`) with the filter's memory dyn: imu_t and q are the batch's (all
    its samples; the epoch's are sliced here), markers the passages to apply (M, 7)."""
    i0, i1 = int(ws[W_I0]), int(ws[W_I1])
    return Context(
        ws_sv[S_LIN].copy(),
        ws_sv[S_MECH],
        L,
        prm,
        ws[W_T],
        ws[W_SPEED],
        ws[W_STOPPED] != 0.0,
        L[L_VEL] >= 0,
        ws[W_HAS_ODO] != 0.0,
        ws[W_EXCLUDED] != 0.0,
        dyn[D_FREE] != 0.0,
        ws[W_LEVER_RATE],
        ws[W_W_YZ],
        ws[W_VJAC : W_VJAC + 3].copy(),
        ws[W_MVB : W_MVB + 3],
        ws[W_GYRO : W_GYRO + 3].copy(),
        ws[W_FMN : W_FMN + 3].copy(),
        ws[W_DP : W_DP + 3],
        ws_m,
        dyn[D_HAS_PREV_VEL] != 0.0,
        dyn[D_PREV_VEL : D_PREV_VEL + 3],
        imu_t[i0:i1],
        q[i0:i1],
        int(ws[W_MAG_I]),
        mag_t,
        mag_f,
        markers,
    )


_context = kernel(context)  # the same, compiled, for _updates


@kernel
def _updates(
    e: int,
    k_ep: int,
    f: Filter,
    L: Index,
    prm: Array,
    ref: Array,
    inp: Inputs,
    markers: Array,
    out: EpochOutputs,
) -> None:
    """Epoch e of the batch from the prediction on: the gated updates (odometer and NHC, zero
    velocity and rate at stops, gravity tilt, magnetic heading, the markers given), injection
    and the epoch's outputs (Navigator's epoch, second half)."""
    sv, x, P, _, dyn = f
    has_ref = ref.shape[0] > 0
    c = _context(out.ws, out.ws_sv, out.ws_m, dyn, L, prm, inp.imu_t, out.q, inp.mag_t,
                 inp.mag_f, markers)  # fmt: skip
    odometer.apply(c, x, P, out)
    zero_velocity.apply(c, x, P, out)
    zero_rate.apply(c, x, P, out)
    gravity_tilt.apply(c, x, P, out)
    magnetic_heading.apply(c, x, P, out)
    marker.apply(c, x, P, out)
    s, s1, T, speed, stopped, dp = c.s, c.s1, c.T, c.speed, c.stopped, c.dp
    omega = out.ws[W_OMEGA : W_OMEGA + 3]
    v_jac = c.v_jac
    if has_ref:
        lin = ref[k_ep]
        est = inject_k(lin, x, L)
        est[SV_DIST] = lin[SV_DIST]
        out.dx[e] = x - out.ws_x
        out.end_offset[e] = difference_k(lin, s1, L)
        out.x_upd[e] = x
    else:
        est = inject_k(s, x, L)
        x[:] = 0.0  # injected: the filter relinearizes about its estimate
        out.dx[e] = difference_k(est, s1, L)
        out.end_offset[e] = out.dx[e]
        out.x_upd[e] = x
    dyn[D_PREV_SPEED] = speed
    dyn[D_PREV_VEL : D_PREV_VEL + 3] = dp / T
    dyn[D_HAS_PREV_VEL] = 1.0
    dyn[D_V_JAC : D_V_JAC + 3] = v_jac
    dyn[D_S_START] = out.s_odo[int(out.ws[W_I1]) - 1]
    sv[:] = est
    out.sv[e] = est
    out.P_upd[e] = P
    out.stopped[e] = stopped
    out.omega[e] = omega
    out.counts[C_EPOCHS] += 1


@kernel(nogil=True)
def run_epochs(
    stop: bool,
    resume: bool,
    k0: int,
    f: Filter,
    L: Index,
    prm: Array,
    ref: Array,
    inp: Inputs,
    markers: Array,
    out: EpochOutputs,
) -> None:
    """The epochs ending at ``ends`` (see the module docstring); epoch e is the filter's epoch
    number k0 + e. stop: leave the last epoch after its prediction (its results in ws, ws_sv,
    ws_x, ws_m); resume: the first epoch's prediction was left so. The markers (M, 7)
    (:func:`measurements.marker.marker_vector`) are applied in the last epoch."""
    B = inp.ends.shape[0]
    for e in range(B):
        if not (resume and e == 0):
            _predict(e, k0 + e, f, L, prm, ref, inp, out)
        if stop and e == B - 1:
            return
        _updates(e, k0 + e, f, L, prm, ref, inp, markers if e == B - 1 else markers[:0], out)
