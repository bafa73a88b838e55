"""Gravity tilt (seed 001 eq. 11-13): the mean specific force rotated into ENU equals the
kinematic acceleration plus the reaction to gravity, m/s^2.

An attitude error rotates both the specific force and the kinematic acceleration (the
odometer's path is laid out with the same attitude), so only their difference, the gravity
reaction, sees it: the update constrains the tilt and, rightly, never the heading. It needs
the odometer (the kinematic acceleration is the change of the epoch's mean velocity) and is
gated (counted) where the motion is strong: specific-force magnitude off gravity, or the
kinematic acceleration, beyond tilt_gate.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements.context import Context, Measurement, factor, update
from pipe_nav_core.model.state import L_AM, L_ATT, L_BA, L_N, SV_H, SV_LAT, Layout, NavState

if TYPE_CHECKING:
    from pipe_nav_core.model.measurements.context import Array, Factor, Index, Model, Tally

KINDS, EVENTS = ("tilt",), ("tilt_gated_motion",)  # its update (statistics), the events it counts

OFF, GATED, ON = 0, 1, 2  # inputs_k's verdicts


@kernel
def gravity_tilt_k(
    sv: Array,
    L: Index,
    f_mean_n: Array,
    c_mean: Array,
    accel_n: Array,
    sigma: float,
    c_f_mean: Array,
) -> Model:
    """:func:`gravity_tilt` on a flat state (c_f_mean (3, 9), or (0, 9) for none)."""
    g = earth._gravity(sv[SV_LAT], sv[SV_H])
    d = f_mean_n - accel_n
    h = d - np.array([0.0, 0.0, g])
    H = np.zeros((3, L[L_N]))
    a, ba, am = L[L_ATT], L[L_BA], L[L_AM]
    H[:, a : a + 3] = -att.skew_k(d)
    H[:, ba : ba + 3] = -c_mean
    if am >= 0 and c_f_mean.shape[0] == 3:
        H[:, am : am + 9] = -c_f_mean
    return -h, H, np.eye(3) * sigma**2


def gravity_tilt(
    s: NavState,
    layout: Layout,
    *,
    f_mean_n: Array,
    c_mean: Array,
    accel_n: Array,
    sigma: float,
    c_f_mean: Array | None = None,
) -> Measurement:
    """The update for a NavState. f_mean_n: mean C_nb (f - ba) over the epoch; c_mean: mean
    C_nb over the epoch; accel_n: the kinematic acceleration from the odometer and attitude
    (ENU); c_f_mean (3, 9): mean of C_nb[:, i] f_j over the epoch, the coupling of the
    accelerometer error matrix (when the layout has it)."""
    f = np.asarray
    r, H, R = gravity_tilt_k(
        s.vector(),
        layout.index,
        f(f_mean_n, dtype=np.float64),
        f(c_mean, dtype=np.float64),
        f(accel_n, dtype=np.float64),
        float(sigma),
        np.zeros((0, 9)) if c_f_mean is None else f(c_f_mean, dtype=np.float64),
    )
    return Measurement("tilt", r, H, R)


@kernel
def inputs_k(c: Context) -> tuple[int, tuple[Array, Array, Array, float, Array]]:
    """OFF (disabled, no odometer or no previous epoch), GATED (strong motion) or ON, and
    gravity_tilt_k's inputs after sv, L."""
    T = c.T
    accel_n = (c.dp / T - c.prev_vel) / T
    f_mean_n = c.f_mean_n
    args = (f_mean_n, c.sums[:, :3] / T, accel_n, c.prm.tilt_sigma, c.sums[:, 3:] / T)
    if not (c.prm.tilt_on and c.odo_ok and c.has_prev_vel):
        return OFF, args
    g = earth._gravity(c.s[SV_LAT], c.s[SV_H])
    f_norm = np.sqrt(np.sum(f_mean_n**2))
    gate = c.prm.tilt_gate
    if abs(f_norm - g) > gate or np.sqrt(np.sum(accel_n**2)) > gate:
        return GATED, args
    return ON, args


# apply and factors have the shape of the other measurements' on purpose: numba takes no kernel
# as an argument without losing its disk cache, so each measurement calls its own model itself
@kernel
def apply(c: Context, x: Array, P: Array, tally: Tally, kind: int, event: int) -> None:
    """The update (counted under kind), or the gated motion counted (event), as
    :func:`inputs_k` says."""
    verdict, args = inputs_k(c)
    if verdict == GATED:
        tally.counts[event] += 1
    elif verdict == ON:
        r, H, R = gravity_tilt_k(c.s, c.L, *args)
        update(kind, r, H, R, x, P, c.prm.chi2, tally)


def factors(c: Context) -> list[Factor]:
    """The update :func:`apply` makes at this context, as a model of the state."""
    verdict, args = inputs_k(c)
    return [factor(KINDS[0], gravity_tilt_k, *args)] if verdict == ON else []
