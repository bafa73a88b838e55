"""Odometer speed with the non-holonomic constraint (INS mode), body frame, m/s.

The mean body velocity over the epoch must equal u(bore) * ((1 + k) * speed - lever_rate):
row 0 is the odometer's speed along the bore axis u, rows 1-2 the non-holonomic constraint
(no velocity across the bore). The two are separate updates: a slip excludes the speed row
(counted) but the pig still cannot move sideways. The speed noise is the configured one
scaled to the epoch (NOISE_EPOCH_S), plus, where the lever arm is unknown, the bend term
(half the pipe diameter times the turn rate across the bore).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.config import NOISE_EPOCH_S
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements.context import Context, Measurement, factor, rows, update
from pipe_nav_core.model.state import (
    I_BORE,
    I_ODOQ,
    I_VEL,
    L_ATT,
    L_BORE,
    L_K,
    L_N,
    L_ODOQ,
    L_VEL,
    SV_K,
    Layout,
    NavState,
    c_nb_k,
    odometer_axis,
)

if TYPE_CHECKING:
    from pipe_nav_core.model.measurements.context import Array, Factor, Index, Model, Tally

KINDS = ("nhc", "odometer")  # its updates (statistics): the NHC rows, the speed row
EVENTS = ("epochs_without_odometer", "odometer_excluded")  # the events it counts
NHC, SPEED = range(len(KINDS))
ROWS = ((1, 3), (0, 1))  # velocity_k's rows lo:hi of each update of KINDS
NO_ODOMETER, EXCLUDED = range(len(EVENTS))


@kernel
def velocity_k(
    sv: Array,
    L: Index,
    lo: int,
    hi: int,
    speed: float,
    vel_b_offset: Array,
    lever_rate: float,
    sigma_speed: float,
    sigma_nhc: float,
    vel_jac: Array,
    epoch_s: float,
) -> Model:
    """Rows lo:hi of the three, the odometer speed (0) and the NHC (1-2), on a flat state
    (ROWS; the other arguments: :func:`velocity`, sigma_speed and sigma_nhc m/s)."""
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
    return rows(-h, H, R, lo, hi)


def velocity(
    s: NavState,
    layout: Layout,
    kind: str,
    *,
    speed: float,
    vel_b_offset: Array,
    lever_rate: float,
    sigma_speed: float = 0.0,
    sigma_nhc: float = 0.0,
    vel_jac: Array | None = None,
    epoch_s: float = 0.0,
) -> Measurement:
    """The update ``kind`` of KINDS ("nhc": rows 1-2, or "odometer": the speed row 0) for a
    NavState, as :func:`apply` makes it (sigma_speed, sigma_nhc m/s).

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
    lo, hi = ROWS[KINDS.index(kind)]
    r, H, R = velocity_k(
        s.vector(),
        layout.index,
        lo,
        hi,
        float(speed),
        np.asarray(vel_b_offset, dtype=np.float64),
        float(lever_rate),
        float(sigma_speed),
        float(sigma_nhc),
        np.asarray(s.vel_n if vel_jac is None else vel_jac, dtype=np.float64),
        float(epoch_s),
    )
    return Measurement(kind, r, H, R)


@kernel
def inputs_k(c: Context) -> tuple[bool, tuple[float, Array, float, float, float, Array, float]]:
    """Whether the epoch has the odometer updates (INS mode, odometer data) and the models'
    inputs after sv, L: the speed and NHC noise for the epoch's duration, the speed's with the
    bend term."""
    prm = c.prm
    bend = 0.0 if prm.lever_known else 0.5 * prm.pipe_d * c.w_yz
    over = np.sqrt(NOISE_EPOCH_S / max(c.T, 1e-3))  # NavConfig.over_epoch
    sigma_speed = np.hypot(prm.odo_sigma * over, bend)
    vel_b_offset = c.mean_vel_b - c_nb_k(c.s1).T @ c.s1[I_VEL : I_VEL + 3]
    args = (c.speed, vel_b_offset, c.lever_rate, sigma_speed, prm.nhc_sigma * over, c.v_jac,
            c.T)  # fmt: skip
    return c.ins and c.odo_ok, args


@kernel
def apply(c: Context, x: Array, P: Array, tally: Tally, kind: int, event: int) -> None:
    """The NHC update, then the speed update unless excluded (counted, as epochs without
    odometer data are); kind, event: where its KINDS and EVENTS start in the statistics."""
    if not c.odo_ok:
        tally.counts[event + NO_ODOMETER] += 1
    on, args = inputs_k(c)
    if not on:
        return
    r, H, R = velocity_k(c.s, c.L, 0, 3, *args)  # the model once, both updates' rows
    lo, hi = ROWS[NHC]
    update(kind + NHC, *rows(r, H, R, lo, hi), x, P, c.prm.chi2, tally)
    if c.excluded:
        tally.counts[event + EXCLUDED] += 1
    else:
        lo, hi = ROWS[SPEED]
        update(kind + SPEED, *rows(r, H, R, lo, hi), x, P, c.prm.chi2, tally)


def factors(c: Context) -> list[Factor]:
    """The updates :func:`apply` makes at this context, as models of the state."""
    on, args = inputs_k(c)
    if not on:
        return []
    ups = (NHC,) if c.excluded else (NHC, SPEED)
    return [factor(KINDS[u], velocity_k, *ROWS[u], *args) for u in ups]
