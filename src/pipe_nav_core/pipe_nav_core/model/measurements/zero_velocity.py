"""Zero velocity at a stop (INS mode): v_n = 0, ENU m/s, noise zupt_sigma."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements.context import Context, Measurement, factor, update
from pipe_nav_core.model.state import I_VEL, L_N, L_VEL, Layout, NavState

if TYPE_CHECKING:
    from pipe_nav_core.model.measurements.context import Array, Factor, Index, Model, Tally

KINDS, EVENTS = ("zupt",), ()  # its update (statistics), the events it counts


@kernel
def zero_velocity_k(sv: Array, L: Index, sigma: float) -> Model:
    """:func:`zero_velocity` on a flat state."""
    H = np.zeros((3, L[L_N]))
    for r in range(3):
        H[r, L[L_VEL] + r] = 1.0
    return -sv[I_VEL : I_VEL + 3].copy(), H, np.eye(3) * sigma**2


def zero_velocity(s: NavState, layout: Layout, sigma: float) -> Measurement:
    """The update for a NavState (sigma m/s)."""
    assert layout.vel is not None
    return Measurement("zupt", *zero_velocity_k(s.vector(), layout.index, float(sigma)))


@kernel
def inputs_k(c: Context) -> tuple[bool, float]:
    """Whether the epoch has the update (stopped, INS mode) and its noise (m/s)."""
    return c.stopped and c.ins, c.prm.zupt


@kernel
def apply(c: Context, x: Array, P: Array, tally: Tally, kind: int, event: int) -> None:
    """The update where :func:`inputs_k` says so, counted under kind."""
    on, sigma = inputs_k(c)
    if on:
        r, H, R = zero_velocity_k(c.s, c.L, sigma)
        update(kind, r, H, R, x, P, c.prm.chi2, tally)


def factors(c: Context) -> list[Factor]:
    """The update :func:`apply` makes at this context, as a model of the state."""
    on, sigma = inputs_k(c)
    return [factor(KINDS[0], zero_velocity_k, sigma)] if on else []
