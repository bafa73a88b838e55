"""Zero angular rate at a stop: the mean gyro reading (rad/s, base_link) equals the Earth rate
seen in the body plus the gyro bias. Its noise is the gyro's angle random walk over the epoch
with zaru_sigma added; while the heading is free (unanchored) its heading column is zeroed: no
gyrocompassing of a heading the filter keeps outside (anchoring.FreeHeading)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements.context import Context, Measurement, factor, update
from pipe_nav_core.model.state import I_BG, L_ATT, L_BG, L_N, SV_LAT, Layout, NavState, c_nb_k

if TYPE_CHECKING:
    from pipe_nav_core.model.measurements.context import Array, Factor, Index, Model, Tally

KINDS, EVENTS = ("zaru",), ()  # its update (statistics), the events it counts


@kernel
def zero_rate_k(
    sv: Array, L: Index, gyro_mean: Array, sigma: float, earth_sign: float, free: bool
) -> Model:
    """:func:`zero_rate` on a flat state (free: the heading column zeroed)."""
    c = c_nb_k(sv)
    w_ie = earth.earth_rate_k(sv[SV_LAT], earth_sign)
    h = gyro_mean - sv[I_BG : I_BG + 3] - c.T @ w_ie
    H = np.zeros((3, L[L_N]))
    for r in range(3):
        H[r, L[L_BG] + r] = -1.0
    a = L[L_ATT]
    H[:, a : a + 3] = -(c.T @ att.skew_k(w_ie))
    if free:
        H[:, a + 2] = 0.0
    return -h, H, np.eye(3) * sigma**2


def zero_rate(
    s: NavState, layout: Layout, *, gyro_mean: Array, sigma: float, earth_sign: float = 1.0
) -> Measurement:
    """The update for a NavState with an anchored heading (gyro_mean rad/s, sigma rad/s)."""
    r, H, R = zero_rate_k(
        s.vector(),
        layout.index,
        np.asarray(gyro_mean, dtype=np.float64),
        float(sigma),
        float(earth_sign),
        False,
    )
    return Measurement("zaru", r, H, R)


@kernel
def inputs_k(c: Context) -> tuple[bool, tuple[Array, float, float, bool]]:
    """Whether the epoch has the update (stopped) and zero_rate_k's inputs after sv, L."""
    prm = c.prm
    sigma = np.sqrt(prm.imu[0] ** 2 / c.T + prm.zaru**2)
    return c.stopped, (c.gyro_mean, sigma, prm.earth_sign, c.free)


@kernel
def apply(c: Context, x: Array, P: Array, tally: Tally, kind: int, event: int) -> None:
    """The update where :func:`inputs_k` says so, counted under kind."""
    on, args = inputs_k(c)
    if on:
        r, H, R = zero_rate_k(c.s, c.L, *args)
        update(kind, r, H, R, x, P, c.prm.chi2, tally)


def factors(c: Context) -> list[Factor]:
    """The update :func:`apply` makes at this context, as a model of the state."""
    on, args = inputs_k(c)
    return [factor(KINDS[0], zero_rate_k, *args)] if on else []
