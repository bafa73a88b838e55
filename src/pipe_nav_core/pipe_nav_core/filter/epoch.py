"""The filter epoch, compiled: mechanize the block of IMU samples, propagate the covariance,
apply the gated updates, inject the correction, write what the smoothers need.

:class:`pipe_nav_core.filter.navigator.Navigator` decides where epochs end, prepares the per-epoch
inputs
(odometer coverage and distance, encoder resolution, excluded slips, magnetometer sample) for a
batch of epochs, and calls :func:`run_epochs` once per batch; the rare events (alignment, the
heading re-anchoring and covariance recovery at a marker passage) stay in Python between
:func:`run_epochs` with ``stop`` (prediction only) and with ``resume`` (updates only). Every
model is the shared one (:mod:`process`, :mod:`measurements`, :mod:`kalman`, :mod:`state`).

An epoch's prediction is two halves: its transition (:func:`_transition`: mechanization, stop
detection, Phi, Qd and the offset, which read no error state) and the propagation of the error
state through it (:func:`_propagate`). About a reference trajectory the transitions depend on
the reference and the data alone, so the Navigator has them made on the other core
(:func:`transition_epochs`) ahead of :func:`run_epochs` with ``ready``.

Arrays (float64 unless said):
- :class:`Filter`: the filter's nominal state, mean error, covariance and memory, updated in
  place;
- ``prm`` the settings (:class:`Settings`, :func:`parameters`); ``L`` the layout
  (Layout.index);
- ``ref`` (K, SV_SIZE) the reference trajectory (empty without one) and ``k0`` the epoch number
  of the batch's first epoch;
- :class:`Inputs`: the batch's IMU samples and per-epoch odometer and magnetometer data;
- :class:`EpochOutputs` (a :class:`Batch`'s arrays): per epoch, per sample (lat, lon, h, q_nb,
  odometer reading) and the update statistics.

The records passed between the prediction, the Python between a stopped and a resumed call,
and the updates are flat arrays whose fields are declared once with their size
(:class:`pipe_nav_core.records.Fields`: D_* the filter's memory, W_* the prediction's
results; integers and flags in int64 arrays); the settings are a typed :class:`Settings`.

About 500 lines, one module on purpose: the compiled epoch loop and its records are read
together, and numba compiles the loop with every function it calls (a split would only move
the records away from the loop that reads them).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.kalman import chi2_threshold, predict_k
from pipe_nav_core.jit import kernel, literal_unroll
from pipe_nav_core.model.measurements import C_EPOCHS, COUNTERS, KINDS, UPDATES
from pipe_nav_core.model.measurements.context import Context, Settings, Tally
from pipe_nav_core.model.measurements.section_direction import restart_k
from pipe_nav_core.model.measurements.straight_pipe import NO_SECTIONS
from pipe_nav_core.model.mechanization import dr_step_k, ins_step_k
from pipe_nav_core.model.process import discretize_k, imu_noise, process_noise_k, system_matrix_k
from pipe_nav_core.model.sensors import ImuSpec
from pipe_nav_core.model.state import (
    I_BG,
    I_VEL,
    L_VEL,
    SV_DIST,
    SV_K,
    SV_SIZE,
    SV_T,
    difference_k,
    inject_k,
)
from pipe_nav_core.records import Fields

Array = NDArray[np.float64]
Index = NDArray[np.int64]

# the filter's memory besides sv, x, P, carry: floats (dyn) and flags (dyn_i, 0 or 1)
_dyn = Fields()
D_PREV_SPEED = _dyn()  # the previous epoch's raw odometer speed, m/s
D_PREV_VEL = _dyn(3)  # the previous epoch's mean ENU velocity, m/s
D_S_START = _dyn()  # the odometer reading at the epoch's start, m
D_V_JAC = _dyn(3)  # the previous first-estimate Jacobian velocity, ENU m/s
D_SLOW_GYRO = _dyn(3)  # the epochs' mean gyro readings so far, low-passed: rad/s base_link
D_SIZE = _dyn.size
_dyn_i = Fields()
D_HAS_PREV_VEL = _dyn_i()  # D_PREV_VEL is set
D_FREE = _dyn_i()  # the heading is unanchored
D_HAS_SLOW_GYRO = _dyn_i()  # D_SLOW_GYRO is set
D_INT_SIZE = _dyn_i.size

# the prediction's results the updates use: floats (ws), integers (ws_i), the states (ws_sv)
_ws = Fields()
W_T = _ws()  # the epoch's duration, s
W_SPEED = _ws()  # the raw mean odometer speed, m/s
W_LEVER_RATE = _ws()  # mean (omega x d)_x of the wheel contact, m/s
W_W_YZ = _ws()  # the turn rate across the bore, rad/s
W_GYRO = _ws(3)  # the time-weighted mean gyro reading, rad/s base_link
W_OMEGA = _ws(3)  # the mean body rate, rad/s base_link
W_MVB = _ws(3)  # the mean body velocity, m/s base_link
W_FMN = _ws(3)  # mean C_nb (f - ba), m/s^2 ENU
W_DP = _ws(3)  # the ENU displacement, m
W_VJAC = _ws(3)  # the first-estimate Jacobian velocity, ENU m/s
W_SLOW_GYRO = _ws(3)  # the epochs' mean gyro readings before this one, low-passed, rad/s
W_SIZE = _ws.size
_ws_i = Fields()
W_I0, W_I1 = _ws_i(), _ws_i()  # the epoch's samples i0:i1 of the batch
W_MAG_I = _ws_i()  # its magnetometer sample (-1 none)
W_STOPPED, W_HAS_ODO, W_EXCLUDED = _ws_i(), _ws_i(), _ws_i()  # flags, 0 or 1
W_INT_SIZE = _ws_i.size
S_MECH, S_LIN = 0, 1  # rows of ws_sv: the mechanized state, the updates' linearization point
# s: the time constant of the low-passed gyro reading (W_SLOW_GYRO), longer than an epoch (so
# that it holds little of any one epoch's noise) and shorter than the pipe's turns last
SLOW_GYRO_S = 1.0


def parameters(
    config: NavConfig,
    imu: ImuSpec,
    lever_arm: Array,
    earth_sign: float,
    mag_ref: tuple[float, float] | None,
    straight: tuple[Array, Array] = (NO_SECTIONS, NO_SECTIONS),
) -> Settings:
    """The settings of the kernels (every number a float, every flag a bool: one compiled
    specialization whatever types the configuration holds); straight: the chainage intervals
    (K, 2; m) straight in plan and in the vertical plane (:func:`straight_pipe.sections`)."""
    c, f = config, float
    ref, dip = (0.0, 0.0) if mag_ref is None else (f(mag_ref[0]), f(mag_ref[1]))
    return Settings(
        earth_sign=f(earth_sign), pipe_d=f(c.pipe_diameter),
        lever=np.array(lever_arm, dtype=np.float64), lever_known=bool(np.any(lever_arm)),
        stop_speed=f(c.stop_speed_threshold), stop_gyro=f(c.stop_gyro_threshold),
        odo_sigma=f(c.odometer_speed_sigma), nhc_sigma=f(c.nhc_sigma),
        zupt=f(c.zupt_sigma), zaru=f(c.zaru_sigma),
        tilt_on=bool(c.tilt_enabled()), tilt_gate=f(c.tilt_gate), tilt_sigma=f(c.tilt_sigma),
        mag_on=bool(c.mag_update), mag_norm_gate=f(c.mag_magnitude_gate),
        mag_dip_gate=f(c.mag_dip_gate), mag_decl=f(c.mag_declination),
        mag_sigma=f(c.mag_heading_sigma), mag_ref=ref, mag_dip=dip,
        mag_ref_ok=mag_ref is not None, scale_rw=f(c.odometer_scale_rw),
        dr_along=f(c.odometer_distance_sigma), dr_lateral=f(c.dr_lateral_sigma),
        marker_time=f(c.marker_time_sigma), straight_sigma=f(c.straight_pipe_sigma),
        straight_h=np.asarray(straight[0], np.float64).reshape(-1, 2),
        straight_v=np.asarray(straight[1], np.float64).reshape(-1, 2),
        straight_wander=f(c.straight_pipe_wander),
        chi2=np.array([chi2_threshold(c.gate_probability, m) for m in (1, 2, 3)]),
        imu=np.array(imu_noise(imu), dtype=np.float64),
    )  # fmt: skip


class Filter(NamedTuple):
    """The filter's memory, updated in place: nominal state ``sv`` (SV_SIZE,), mean error ``x``
    (n,), covariance ``P`` (n, n), the previous block's last increments ``carry`` (6,) and the
    rest, ``dyn`` (D_SIZE,) and ``dyn_i`` (D_INT_SIZE,) (the D_* fields)."""

    sv: Array
    x: Array
    P: Array
    carry: Array
    dyn: Array
    dyn_i: Index


class Inputs(NamedTuple):
    """A batch's data: IMU samples (base_link; s, rad/s, m/s^2) from just after the state's
    time, each epoch's last sample ``ends``, the odometer reading at every sample ``s_odo``
    (m); per epoch ``has_odo``, ``still`` (the odometer stands still over it and a margin
    either side: a stop may be claimed), ``excluded`` (slip), encoder ``resolution`` (m) and
    magnetometer sample ``mag_i`` (-1 none) into ``mag_t`` (s) / ``mag_f`` (T, base_link)."""

    imu_t: Array
    imu_g: Array
    imu_a: Array
    ends: Index
    s_odo: Array
    has_odo: NDArray[np.bool_]
    still: NDArray[np.bool_]
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
    ws_i: Index
    ws_sv: Array
    ws_x: Array
    ws_m: Array
    fac: Array
    fac_i: Index
    fac_n: Index
    tr_qd: Array
    tr_offset: Array
    tr_ws: Array
    tr_ws_i: Index
    tr_ws_sv: Array
    tr_ws_m: Array


class Prediction(NamedTuple):
    """What an epoch's prediction leaves its updates besides the states, the mean error and
    the sums (ws_sv, ws_x, ws_m): the W_* fields of ws and ws_i (:func:`_keep`)."""

    T: float
    speed: float
    lever_rate: float
    w_yz: float
    gyro_mean: Array
    omega: Array
    mean_vel_b: Array
    f_mean_n: Array
    dp: Array
    v_jac: Array
    gyro_slow: Array
    i0: int
    i1: int
    mag_i: int
    stopped: bool
    has_odo: bool
    excluded: bool


class Batch:
    """Output buffers of :func:`run_epochs` for up to ``size`` epochs and ``samples`` IMU
    samples: per epoch the estimate ``sv`` (after the update), ``x_upd`` (the filter's mean
    error after the updates), ``dx`` (what the updates moved, the RTS smoother's
    correction), ``end_offset``, ``P_pred``, ``P_upd``, ``phi``, ``stopped``, ``omega``
    (rad/s base_link); per sample ``lat``, ``lon`` (rad), ``h`` (m), ``q`` and the odometer
    reading ``s_odo`` (m); marker residuals (ENU m) per marker of the call; counters and
    update statistics (``acc``, ``rej``, ``nis``, ``dof`` per kind of KINDS); with
    ``factors``, room for that many updates recorded (:func:`linearize_epochs`): ``fac``
    (factors, 3, n + 4) the rows of each update's H (n columns), r (1) and R (3), ``fac_i``
    (factors, 3) its kind (index into KINDS), rows and epoch of the batch, ``fac_n`` (1,)
    how many; the epochs' transitions as :func:`_transition` leaves them for
    :func:`_propagate` (``tr_*``: qd, offset, ws, ws_i, ws_sv, ws_m; a row per epoch with
    ``transitions`` (for :func:`transition_epochs`), else one row that each epoch reuses)."""

    def __init__(
        self, size: int, samples: int, n: int, factors: int = 0, transitions: bool = False
    ) -> None:
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
        self.ws_i = np.zeros(W_INT_SIZE, dtype=np.int64)
        self.ws_sv = np.zeros((2, SV_SIZE))
        self.ws_x = np.zeros(n)
        self.ws_m = np.zeros((3, 12))
        self.fac = np.zeros((factors, 3, n + 4))
        self.fac_i = np.zeros((factors, 3), dtype=np.int64)
        self.fac_n = np.zeros(1, dtype=np.int64)
        rows = size if transitions else 1
        self.tr_qd = np.zeros((rows, n, n))
        self.tr_offset = np.zeros((rows, n))
        self.tr_ws = np.zeros((rows, W_SIZE))
        self.tr_ws_i = np.zeros((rows, W_INT_SIZE), dtype=np.int64)
        self.tr_ws_sv = np.zeros((rows, 2, SV_SIZE))
        self.tr_ws_m = np.zeros((rows, 3, 12))

    def reset(self) -> None:
        """Zero the counters and statistics (before reusing the buffers)."""
        for a in (self.counts, self.acc, self.rej, self.nis, self.dof, self.fac_n):
            a[:] = 0

    def buffers(self) -> EpochOutputs:
        """The arrays, as run_epochs takes them."""
        return EpochOutputs(*(getattr(self, name) for name in EpochOutputs._fields))


@kernel
def _transition(
    e: int,
    k_ep: int,
    row: int,
    sv: Array,
    carry: Array,
    dyn: Array,
    dyn_i: Index,
    L: Index,
    prm: Settings,
    ref: Array,
    inp: Inputs,
    out: EpochOutputs,
) -> None:
    """Epoch e of the batch up to its transition: mechanization, stop detection, transition
    matrix (out.phi[e]), process noise and the offset from the linearization point, and what
    the updates read (into the transition rows ``row``, out.tr_*; the per-sample outputs
    into theirs). It reads no error state: about a reference trajectory it depends on the
    reference and the data alone (and on carry and the previous epoch's odometer reading,
    speed and Jacobian velocity in dyn, which it updates as the epoch's updates will)."""
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
    earth_sign = prm.earth_sign
    if ins:
        step = ins_step_k(s0, t, g, inp.imu_a[i0:i1], carry, earth_sign)
    else:
        step = dr_step_k(s0, t, g, inp.imu_a[i0:i1], ds, carry, prm.lever, earth_sign)
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
    lever_known = prm.lever_known
    bend_sigma = 0.0 if lever_known else 0.5 * prm.pipe_d * w_yz * T
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
    thr = prm.stop_speed
    stopped = (
        odo_ok
        and inp.still[e]
        and abs(speed) < thr
        and abs(dyn[D_PREV_SPEED]) < thr
        and np.sqrt(dg[0] ** 2 + dg[1] ** 2 + dg[2] ** 2) < prm.stop_gyro
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
        dyn_i[D_FREE] != 0,
    )
    Q = process_noise_k(
        s0,
        L,
        T,
        sum_c_dt,
        path,
        prm.imu,
        prm.scale_rw,
        prm.dr_along,
        prm.dr_lateral,
        bend_sigma,
        inp.resolution[e],
        prm.straight_wander,
    )
    phi, qd = discretize_k(A, Q, L)
    # a straight section entered: its direction starts afresh from the axis
    d1 = s_lin[SV_DIST] if has_ref else s0[SV_DIST] + (1.0 + s0[SV_K]) * ds.sum()
    restart_k(prm, L, s0[SV_DIST], d1, s1, phi, qd)
    out.phi[e] = phi
    out.tr_qd[row] = qd
    if has_ref:
        out.tr_offset[row] = difference_k(s1, s_lin, L)
    else:
        out.tr_offset[row] = 0.0
    s1[SV_DIST] = s0[SV_DIST] + (1.0 + s0[SV_K]) * ds.sum()
    out.tr_ws_sv[row, S_MECH] = s1
    out.tr_ws_sv[row, S_LIN] = s_lin
    lever = prm.lever
    lever_rate = omega_b[1] * lever[2] - omega_b[2] * lever[1]  # (omega x d)_x
    gyro_slow = dyn[D_SLOW_GYRO : D_SLOW_GYRO + 3].copy() if dyn_i[D_HAS_SLOW_GYRO] else gyro_mean
    p = Prediction(T, speed, lever_rate, w_yz, gyro_mean, omega_b, mean_vel_b, f_mean_n, dp,
                   v_jac, gyro_slow, i0, i1, inp.mag_i[e], stopped, odo_ok,
                   inp.excluded[e])  # fmt: skip
    _keep(p, out.tr_ws[row], out.tr_ws_i[row])
    out.tr_ws_m[row, :, :3] = sum_c_dt  # for the tilt update: C_mean and the accelerometer
    out.tr_ws_m[row, :, 3:] = sum_c_f_dt  # coupling
    # what the epoch's updates set in the filter's memory, the next transition reads
    dyn[D_PREV_SPEED] = speed
    dyn[D_V_JAC : D_V_JAC + 3] = v_jac
    dyn[D_S_START] = out.s_odo[i1 - 1]
    _slow_gyro(dyn, dyn_i, gyro_slow, gyro_mean, T)


@kernel
def _slow_gyro(dyn: Array, dyn_i: Index, before: Array, gyro_mean: Array, T: float) -> None:
    """The low-passed gyro reading (dyn's D_SLOW_GYRO, rad/s) after an epoch of T s whose mean
    reading was gyro_mean, from ``before``: what the transition and the updates both set."""
    a = 1.0 - np.exp(-T / SLOW_GYRO_S)
    dyn[D_SLOW_GYRO : D_SLOW_GYRO + 3] = before + a * (gyro_mean - before)
    dyn_i[D_HAS_SLOW_GYRO] = 1


@kernel
def _propagate(e: int, row: int, f: Filter, out: EpochOutputs) -> None:
    """Epoch e's prediction from its transition (rows ``row`` of out.tr_*, :func:`_transition`):
    x <- phi x + offset, P <- phi P phi^T + qd (out.P_pred[e]), and the records the updates
    read (out.ws, ws_i, ws_sv, ws_m, ws_x)."""
    x, P = f.x, f.P
    predict_k(x, P, out.phi[e], out.tr_qd[row], out.tr_offset[row])
    out.P_pred[e] = P
    out.ws_x[:] = x
    out.ws[:] = out.tr_ws[row]
    out.ws_i[:] = out.tr_ws_i[row]
    out.ws_sv[:] = out.tr_ws_sv[row]
    out.ws_m[:] = out.tr_ws_m[row]


@kernel
def _predict(
    e: int,
    k_ep: int,
    f: Filter,
    L: Index,
    prm: Settings,
    ref: Array,
    inp: Inputs,
    out: EpochOutputs,
) -> None:
    """Epoch e of the batch up to the prediction (Navigator's epoch, first half):
    :func:`_transition` into the first transition rows, then :func:`_propagate`."""
    _transition(e, k_ep, 0, f.sv, f.carry, f.dyn, f.dyn_i, L, prm, ref, inp, out)
    _propagate(e, 0, f, out)


@kernel
def _keep(p: Prediction, ws: Array, ws_i: Index) -> None:
    """The prediction's results into their record (ws, ws_i), where the updates and the Python
    between a stopped and a resumed call read them."""
    ws[W_T], ws[W_SPEED], ws[W_LEVER_RATE], ws[W_W_YZ] = p.T, p.speed, p.lever_rate, p.w_yz
    ws[W_GYRO : W_GYRO + 3] = p.gyro_mean
    ws[W_OMEGA : W_OMEGA + 3] = p.omega
    ws[W_MVB : W_MVB + 3] = p.mean_vel_b
    ws[W_FMN : W_FMN + 3] = p.f_mean_n
    ws[W_DP : W_DP + 3] = p.dp
    ws[W_VJAC : W_VJAC + 3] = p.v_jac
    ws[W_SLOW_GYRO : W_SLOW_GYRO + 3] = p.gyro_slow
    ws_i[W_I0], ws_i[W_I1], ws_i[W_MAG_I] = p.i0, p.i1, p.mag_i
    ws_i[W_STOPPED], ws_i[W_HAS_ODO], ws_i[W_EXCLUDED] = p.stopped, p.has_odo, p.excluded


def context(
    ws: Array,
    ws_i: Index,
    ws_sv: Array,
    ws_m: Array,
    dyn: Array,
    dyn_i: Index,
    L: Index,
    prm: Settings,
    imu_t: Array,
    q: Array,
    mag_t: Array,
    mag_f: Array,
    markers: Array,
) -> Context:
    """The measurements' context of the epoch whose prediction left ws, ws_i, ws_sv, ws_m (a
    Batch's, :func:`_predict`) with the filter's memory dyn, dyn_i: imu_t and q are the batch's (all
    its samples; the epoch's are sliced here), markers the passages to apply (M, 7)."""
    i0, i1 = ws_i[W_I0], ws_i[W_I1]
    return Context(
        ws_sv[S_LIN].copy(),
        ws_sv[S_MECH],
        L,
        prm,
        ws[W_T],
        ws[W_SPEED],
        ws_i[W_STOPPED] != 0,
        L[L_VEL] >= 0,
        ws_i[W_HAS_ODO] != 0,
        ws_i[W_EXCLUDED] != 0,
        dyn_i[D_FREE] != 0,
        ws[W_LEVER_RATE],
        ws[W_W_YZ],
        ws[W_VJAC : W_VJAC + 3].copy(),
        ws[W_MVB : W_MVB + 3],
        ws[W_GYRO : W_GYRO + 3].copy(),
        ws[W_SLOW_GYRO : W_SLOW_GYRO + 3].copy(),
        ws[W_FMN : W_FMN + 3].copy(),
        ws[W_DP : W_DP + 3],
        ws_m,
        dyn_i[D_HAS_PREV_VEL] != 0,
        dyn[D_PREV_VEL : D_PREV_VEL + 3],
        imu_t[i0:i1],
        q[i0:i1],
        ws_i[W_MAG_I],
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
    prm: Settings,
    ref: Array,
    inp: Inputs,
    markers: Array,
    out: EpochOutputs,
) -> None:
    """Epoch e of the batch from the prediction on: the gated updates (odometer and NHC, zero
    velocity and rate at stops, gravity tilt, magnetic heading, the markers given), injection
    and the epoch's outputs (Navigator's epoch, second half)."""
    sv, x, P, _, dyn, dyn_i = f
    has_ref = ref.shape[0] > 0
    c = _context(out.ws, out.ws_i, out.ws_sv, out.ws_m, dyn, dyn_i, L, prm, inp.imu_t, out.q,
                 inp.mag_t, inp.mag_f, markers)  # fmt: skip
    tally = Tally(out.counts, out.acc, out.rej, out.nis, out.dof, out.marker_res, out.fac,
                  out.fac_i, out.fac_n)  # fmt: skip
    for u in literal_unroll(UPDATES):  # straight calls, in their order: (kind, event, apply)
        u[2](c, x, P, tally, u[0], u[1])
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
    dyn_i[D_HAS_PREV_VEL] = 1
    dyn[D_V_JAC : D_V_JAC + 3] = v_jac
    dyn[D_S_START] = out.s_odo[out.ws_i[W_I1] - 1]
    _slow_gyro(dyn, dyn_i, c.gyro_slow, c.gyro_mean, T)
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
    ready: bool,
    e0: int,
    e1: int,
    k0: int,
    f: Filter,
    L: Index,
    prm: Settings,
    ref: Array,
    inp: Inputs,
    markers: Array,
    out: EpochOutputs,
) -> None:
    """The epochs e0 to e1 - 1 of those ending at ``ends`` (see the module docstring); epoch
    e is the filter's epoch number k0 + e. stop: leave the last epoch after its prediction
    (its results in ws, ws_sv, ws_x, ws_m); resume: the first epoch's prediction was left
    so; ready: their transitions are in out's transition rows already
    (:func:`transition_epochs`). The markers (M, 7)
    (:func:`measurements.marker.marker_vector`) are applied in the batch's last epoch."""
    B = inp.ends.shape[0]
    for e in range(e0, e1):
        if ready:
            _propagate(e, e, f, out)
        elif not (resume and e == e0):
            _predict(e, k0 + e, f, L, prm, ref, inp, out)
        if stop and e == B - 1:
            return
        _updates(e, k0 + e, f, L, prm, ref, inp, markers if e == B - 1 else markers[:0], out)


@kernel(nogil=True)
def transition_epochs(
    e0: int,
    e1: int,
    k0: int,
    sv: Array,
    carry: Array,
    dyn: Array,
    dyn_i: Index,
    L: Index,
    prm: Settings,
    ref: Array,
    inp: Inputs,
    out: EpochOutputs,
) -> None:
    """The transitions of epochs e0 to e1 - 1 (:func:`_transition`, epoch e into transition
    row e) from the filter's memory carry, dyn, dyn_i (updated as the epochs run): about a
    reference trajectory they do not depend on the error state, so that they are made on
    one core while :func:`run_epochs` with ``ready`` applies the ones before on the other
    (sv: the filter's nominal state, read only without a reference)."""
    for e in range(e0, e1):
        _transition(e, k0 + e, e, sv, carry, dyn, dyn_i, L, prm, ref, inp, out)


@kernel(nogil=True)
def linearize_epochs(
    k0: int,
    f: Filter,
    L: Index,
    prm: Settings,
    ref: Array,
    inp: Inputs,
    out: EpochOutputs,
    offset: Array,
) -> None:
    """:func:`run_epochs` of a batch without markers about a reference trajectory ``ref``,
    every epoch from zero error and covariance: what the batch smoother linearizes
    (pipe_nav_core.graph.linearize). Epoch e leaves its transition in out.phi[e], its
    process noise in out.P_pred[e] (predicted from zero covariance) and its offset (the
    mechanization from ref[k - 1] minus ref[k], predicted from zero error) in offset[e]
    (B, n); the updates it would apply are recorded instead (out.fac, out.fac_i with e in
    column 2, out.fac_n: :func:`.context.update`) when out.fac has rows: no more is read of
    an epoch, whose error and covariance the next one sets to zero again."""
    no_markers = np.zeros((0, 7))
    for e in range(inp.ends.shape[0]):
        f.x[:] = 0.0
        f.P[:] = 0.0
        _predict(e, k0 + e, f, L, prm, ref, inp, out)
        offset[e] = out.ws_x
        j0 = out.fac_n[0]
        _updates(e, k0 + e, f, L, prm, ref, inp, no_markers, out)
        out.fac_i[j0 : min(out.fac_n[0], out.fac.shape[0]), 2] = e
