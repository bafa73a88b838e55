"""What every measurement shares: the epoch's context it reads, the settings, and the one
gated update it applies.

Frames: ENU navigation frame, base_link body frame (FLU). Units SI, angles rad.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.filter.kalman import joseph_in_place
from pipe_nav_core.jit import kernel

Array = NDArray[np.float64]
Index = NDArray[np.int64]
Model = tuple[Array, Array, Array]  # residual (m,), H (m, n), R (m, m)
Factor = tuple[str, Callable[[Array, Index], Model]]  # kind, model at a flat state and layout


class Settings(NamedTuple):
    """The settings of the compiled epoch (built once per pass by
    :func:`pipe_nav_core.filter.epoch.parameters`; NavConfig's, SI units).

    earth_sign: 1, or -1 for the backward filter's reversed time; pipe_d: pipe diameter (m);
    lever: the odometer wheel's lever arm (m, base_link) and lever_known whether it is set;
    stop_speed (m/s) / stop_gyro (rad/s): the stop detection's thresholds; odo_sigma (m/s),
    nhc_sigma (m/s), zupt (m/s), zaru (rad/s): the noise of those updates; tilt_on, tilt_gate
    (m/s^2), tilt_sigma (m/s^2): the gravity tilt update; mag_on, mag_norm_gate (relative),
    mag_dip_gate (rad), mag_decl (rad), mag_sigma (rad), mag_ref (T) / mag_dip (rad) the
    reference field and mag_ref_ok whether it is known: the magnetic heading update;
    scale_rw, dr_along, dr_lateral: process noise of the odometer scale and of dead reckoning;
    marker_time (s): the marker passages' time noise; straight_sigma (rad/s, 0: off),
    straight_h / straight_v (K, 2): the straight-pipe update's noise and the chainage
    intervals (m) straight in plan and in the vertical plane; straight_wander (rad/sqrt(m), 0:
    off): how far a straight section's direction may turn; chi2 (3,): the innovation gates for 1,
    2 and 3 rows; imu (6,): process_noise_k's IMU densities (imu[0]: the gyro's angle random
    walk, rad/sqrt(s))."""

    earth_sign: float
    pipe_d: float
    lever: Array
    lever_known: bool
    stop_speed: float
    stop_gyro: float
    odo_sigma: float
    nhc_sigma: float
    zupt: float
    zaru: float
    tilt_on: bool
    tilt_gate: float
    tilt_sigma: float
    mag_on: bool
    mag_norm_gate: float
    mag_dip_gate: float
    mag_decl: float
    mag_sigma: float
    mag_ref: float
    mag_dip: float
    mag_ref_ok: bool
    scale_rw: float
    dr_along: float
    dr_lateral: float
    marker_time: float
    straight_sigma: float
    straight_h: Array
    straight_v: Array
    straight_wander: float
    chi2: Array
    imu: Array


@dataclass
class Measurement:
    """One update: name (for statistics), residual (m,), H (m, n), R (m, m)."""

    name: str
    residual: Array
    H: Array
    R: Array


class Context(NamedTuple):
    """One epoch as its measurements see it, after the prediction (built by
    :func:`pipe_nav_core.filter.epoch.context`).

    s: the flat state every update is linearized at; s1: the mechanized state at the epoch
    end; L: the layout (Layout.index); prm: the settings; T: the epoch's duration (s);
    speed: the raw mean odometer speed (m/s); stopped: the pig stands still; ins: the layout
    has a velocity error; odo_ok: the epoch has odometer data; excluded: its odometer speed is
    excluded (a slip); free: the heading is unanchored (its prior kept outside the filter);
    lever_rate: mean (omega x d)_x of the wheel contact (m/s); w_yz: the body's turn rate
    across the bore (rad/s); v_jac: the first-estimate Jacobian velocity (ENU m/s);
    mean_vel_b: the mean body velocity over the epoch (m/s); gyro_mean: the time-weighted mean
    gyro reading (rad/s, base_link); gyro_slow: the readings of the epochs before, low-passed
    (rad/s, base_link; epoch.SLOW_GYRO_S): a rate that holds none of this epoch's noise;
    f_mean_n: mean C_nb (f - ba) (m/s^2); dp: the epoch's
    ENU displacement (m); sums: (3, 12) the sums of C_nb dt and C_nb[:, i] f_j dt over the
    epoch; has_prev_vel / prev_vel: the previous epoch's mean ENU velocity (m/s); imu_t / q:
    the epoch's sample times (s) and attitude quaternions; mag_i: its magnetometer sample
    (-1 none) into mag_t (s) / mag_f (T, base_link); markers: (M, 7) the marker passages to
    apply (:func:`marker.marker_vector`)."""

    s: Array
    s1: Array
    L: Index
    prm: Settings
    T: float
    speed: float
    stopped: bool
    ins: bool
    odo_ok: bool
    excluded: bool
    free: bool
    lever_rate: float
    w_yz: float
    v_jac: Array
    mean_vel_b: Array
    gyro_mean: Array
    gyro_slow: Array
    f_mean_n: Array
    dp: Array
    sums: Array
    has_prev_vel: bool
    prev_vel: Array
    imu_t: Array
    q: Array
    mag_i: int
    mag_t: Array
    mag_f: Array
    markers: Array


class Tally(NamedTuple):
    """What the updates write besides x and P (:func:`update`; the arrays of
    epoch.EpochOutputs): counts the events (measurements.COUNTERS); per kind
    (measurements.KINDS) acc / rej the updates applied and gated out, nis / dof their NIS and
    rows summed; marker_res (M, 3) the markers' residuals (m, ENU); fac, fac_i, fac_n the
    updates recorded as factors instead (epoch.linearize_epochs). A record of its own so that
    each call passes these nine arrays, not the epoch's every output."""

    counts: Index
    acc: Index
    rej: Index
    nis: Array
    dof: Index
    marker_res: Array
    fac: Array
    fac_i: Index
    fac_n: Index


@kernel
def update(
    kind: int, r: Array, H: Array, R: Array, x: Array, P: Array, chi2: Array, tally: Tally
) -> None:
    """One gated update of (x, P) in place (gate: chi2[m - 1] for m rows, Settings.chi2),
    counted under kind in the tally. Where the tally records the updates instead
    (epoch.linearize_epochs: tally.fac has rows), the update is not applied but kept, ungated,
    as the batch smoother's factor: r, H, R in tally.fac's next row, its kind and rows in
    tally.fac_i's, counted in tally.fac_n (also beyond tally.fac's rows, which are then not
    written)."""
    m = r.shape[0]
    if tally.fac.shape[0] > 0:
        j = tally.fac_n[0]
        tally.fac_n[0] = j + 1
        if j < tally.fac.shape[0]:
            n = H.shape[1]
            tally.fac[j, :m, :n] = H
            tally.fac[j, :m, n] = r
            tally.fac[j, :m, n + 1 : n + 1 + m] = R
            tally.fac_i[j, 0] = kind
            tally.fac_i[j, 1] = m
        return
    nis, applied = joseph_in_place(P, x, H, R, r, chi2[m - 1], np.empty(x.shape[0]))
    if not applied:
        tally.rej[kind] += 1
        return
    tally.acc[kind] += 1
    tally.nis[kind] += nis
    tally.dof[kind] += m


def factor(kind: str, model_k: Callable[..., Model], *args: object) -> Factor:
    """(kind, its model at a flat state and layout): the kernel ``model_k`` called with
    (sv, L) and then ``args``, the inputs its measurement's policy chose."""
    return kind, lambda sv, L: model_k(sv, L, *args)


@kernel
def rows(r: Array, H: Array, R: Array, lo: int, hi: int) -> Model:
    """Rows lo:hi of a measurement (residual, H, R), applied as an update of their own."""
    return r[lo:hi], H[lo:hi].copy(), R[lo:hi, lo:hi].copy()
