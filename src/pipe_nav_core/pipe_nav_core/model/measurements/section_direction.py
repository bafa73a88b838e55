"""Section direction: a straight pipe keeps one direction from bend to bend, so the pig's
direction of travel does too (the odometer's axis u(boresight) in base_link: where the IMU
sits askew in the pig, base_link x cones about the pipe's axis as the pig rolls, and the
boresight is seen by that). The straight-pipe update (:mod:`.straight_pipe`) holds the body's
turn rate to zero, which binds the gyro's bias but not the heading the gyro's angle random
walk has already turned; this update holds the direction of travel to a state that every
epoch of the section shares, so that the smoother averages that walk away over the whole
section.

The state is the layout's ``dir`` block (:mod:`pipe_nav_core.model.state`): the section's
azimuth (from north, clockwise) and pitch (up), rad, ENU. It starts afresh (:func:`restart_k`:
its transition row zeroed, RESTART_SIGMA of process noise, the nominal set to the axis) in the
epoch whose chainage enters a straight interval of :func:`.straight_pipe.sections`, and
within the section wanders by ``straight_pipe_wander`` (rad per sqrt(m) of path: the pipe's
joints are straight, not their welds' small angles; :func:`.process.process_noise_k`).

The rows (rad) are the travel direction's azimuth minus the section's where the pipe is
straight in plan, and its pitch minus the section's where it is straight in its vertical
plane. Their noise is the pig's wobble about the pipe's axis: as far as the section may turn
over WOBBLE_M of pipe, drawn once per WOBBLE_M (longer epochs see it averaged; shorter ones
share it).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements.context import Context, factor, update
from pipe_nav_core.model.measurements.straight_pipe import section_of
from pipe_nav_core.model.state import (
    I_DIR,
    L_ATT,
    L_BORE,
    L_DIR,
    L_N,
    SV_DIST,
    travel_axis_k,
)

if TYPE_CHECKING:
    from pipe_nav_core.model.measurements.context import (
        Array,
        Factor,
        Index,
        Model,
        Settings,
        Tally,
    )

KINDS, EVENTS = ("direction",), ()  # its update (statistics), the events it counts
RESTART_SIGMA = 1.0  # rad: a new section's direction before its first row (free)
WOBBLE_M = 1.0  # m of pipe over which the pig's wobble is one independent draw


@kernel
def direction_angles_k(t: Array) -> tuple[float, float, float]:
    """The azimuth (from north, clockwise) and pitch (up) of a unit direction t in ENU, rad,
    and its horizontal length (0: vertical, no azimuth)."""
    h = np.hypot(t[0], t[1])
    return np.arctan2(t[0], t[1]), np.arctan2(t[2], h), h


@kernel
def axis_angles_k(sv: Array) -> tuple[float, float, float]:
    """:func:`direction_angles_k` of the direction of travel (:func:`travel_axis_k`)."""
    return direction_angles_k(travel_axis_k(sv)[0])


@kernel
def section_direction_k(sv: Array, L: Index, plan: bool, vertical: bool, sigma: float) -> Model:
    """The travel direction's azimuth minus the section's (if plan) and pitch minus the
    section's (if vertical), rad, zero on a straight pipe: residual, H (attitude, boresight
    and section direction columns) and R (sigma rad on each row)."""
    t, dt_bore = travel_axis_k(sv)
    te, tn, tu = t[0], t[1], t[2]
    azimuth, pitch, h = direction_angles_k(t)
    m = int(plan) + int(vertical)
    r = np.zeros(m)
    H = np.zeros((m, L[L_N]))
    a, d, b = L[L_ATT], L[L_DIR], L[L_BORE]
    i = 0
    if plan:  # d azimuth = (tn dte - te dtn) / h^2 with dt = phi x t, or dt_bore d bore
        r[i] = -(np.mod(azimuth - sv[I_DIR] + np.pi, 2.0 * np.pi) - np.pi)
        H[i, a], H[i, a + 1], H[i, a + 2] = te * tu / h**2, tn * tu / h**2, -1.0
        if b >= 0:
            for j in range(2):
                H[i, b + j] = (tn * dt_bore[0, j] - te * dt_bore[1, j]) / h**2
        H[i, d] = -1.0
        i += 1
    if vertical:  # d pitch = dtu / h (dt is normal to t)
        r[i] = -(pitch - sv[I_DIR + 1])
        H[i, a], H[i, a + 1] = tn / h, -te / h
        if b >= 0:
            for j in range(2):
                H[i, b + j] = dt_bore[2, j] / h
        H[i, d + 1] = -1.0
    return r, H, np.eye(m) * sigma**2


@kernel
def restart_k(
    prm: Settings, L: Index, d0: float, d1: float, s1: Array, phi: Array, qd: Array
) -> None:
    """Start the section direction afresh in an epoch from chainage d0 to d1 (m) that enters
    a straight interval (in plan: the azimuth; in the vertical plane: the pitch): its row of
    phi zeroed, RESTART_SIGMA^2 its process noise, uncorrelated, and its nominal in the
    mechanized state s1 the travel direction's angle."""
    j = L[L_DIR]
    if j < 0 or prm.straight_wander <= 0.0:
        return
    azimuth, pitch, _ = axis_angles_k(s1)
    for r, sections, angle in ((0, prm.straight_h, azimuth), (1, prm.straight_v, pitch)):
        now = section_of(sections, d1)
        if now >= 0 and now != section_of(sections, d0):
            phi[j + r, :] = 0.0
            qd[j + r, :] = 0.0
            qd[:, j + r] = 0.0
            qd[j + r, j + r] = RESTART_SIGMA**2
            s1[I_DIR + r] = angle


@kernel
def inputs_k(c: Context) -> tuple[bool, tuple[bool, bool, float]]:
    """Whether the epoch has the update (moving, in a straight section in plan or in its
    vertical plane, the axis not vertical) and section_direction_k's inputs after sv, L."""
    prm = c.prm
    if prm.straight_wander <= 0.0 or c.L[L_DIR] < 0 or c.stopped or c.T <= 0.0:
        return False, (False, False, 0.0)
    d = c.s[SV_DIST]
    plan = section_of(prm.straight_h, d) >= 0
    vertical = section_of(prm.straight_v, d) >= 0
    if not (plan or vertical) or axis_angles_k(c.s)[2] < 1e-6:
        return False, (False, False, 0.0)
    step = abs(c.speed) * c.T
    wobble = prm.straight_wander * np.sqrt(WOBBLE_M)
    sigma = wobble * np.sqrt(max(1.0, WOBBLE_M / max(step, 1e-9)))
    return True, (plan, vertical, sigma)


@kernel
def apply(c: Context, x: Array, P: Array, tally: Tally, kind: int, event: int) -> None:
    """The update where :func:`inputs_k` says so, counted under kind."""
    on, args = inputs_k(c)
    if on:
        r, H, R = section_direction_k(c.s, c.L, *args)
        update(kind, r, H, R, x, P, c.prm.chi2, tally)


def factors(c: Context) -> list[Factor]:
    """The update :func:`apply` makes at this context, as a model of the state."""
    on, args = inputs_k(c)
    return [factor(KINDS[0], section_direction_k, *args)] if on else []
