"""Magnetic heading (seed 001 eq. 10): the horizontal direction of the measured field, rotated
into ENU with the estimated attitude, equals magnetic north (declination east of true north
positive), rad.

Applied with the magnetometer enabled, a reference field known and a sample in the epoch,
unless the field is disturbed (counted): its magnitude off the reference by more than
mag_magnitude_gate (relative), or its dip off the reference dip by more than mag_dip_gate.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.geo import attitude as att
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements.context import Context, Measurement, factor, update
from pipe_nav_core.model.state import L_ATT, L_N, Layout, NavState

if TYPE_CHECKING:
    from pipe_nav_core.model.measurements.context import Array, Factor, Index, Model, Tally

KINDS, EVENTS = ("mag",), ("mag_disturbed",)  # its update (statistics), the events it counts

OFF, GATED, ON = 0, 1, 2  # inputs_k's verdicts


@kernel
def magnetic_heading_k(
    sv: Array, L: Index, field_b: Array, c_nb: Array, declination: float, sigma: float
) -> Model:
    """:func:`magnetic_heading` on a flat state."""
    m = c_nb @ field_b
    rho2 = m[0] ** 2 + m[1] ** 2
    x = np.arctan2(m[0], m[1]) - declination
    h = np.array([np.arctan2(np.sin(x), np.cos(x))])
    g = np.array([m[1], -m[0], 0.0]) / rho2
    H = np.zeros((1, L[L_N]))
    a = L[L_ATT]
    H[0, a : a + 3] = -(g @ att.skew_k(m))
    return -h, H, np.array([[sigma**2]])


def magnetic_heading(
    s: NavState,
    layout: Layout,
    *,
    field_b: Array,
    c_nb: Array,
    declination: float,
    sigma: float,
) -> Measurement:
    """The update for a NavState. field_b: hard-iron corrected field in base_link (tesla);
    c_nb: the attitude at the magnetometer sample time."""
    r, H, R = magnetic_heading_k(
        s.vector(),
        layout.index,
        np.asarray(field_b, dtype=np.float64),
        np.ascontiguousarray(c_nb, dtype=np.float64),
        float(declination),
        float(sigma),
    )
    return Measurement("mag", r, H, R)


@kernel
def inputs_k(c: Context) -> tuple[int, tuple[Array, Array, float, float]]:
    """OFF, GATED (disturbed) or ON, and magnetic_heading_k's inputs after sv, L: the field
    and the mechanized attitude at the first sample not before the magnetometer's."""
    prm = c.prm
    cnb = np.empty((3, 3))
    m_b = np.zeros(3)
    if not (prm.mag_on and c.mag_i >= 0 and prm.mag_ref_ok):
        return OFF, (m_b, cnb, prm.mag_decl, prm.mag_sigma)
    n = c.imu_t.shape[0]
    j = 0
    while j < n - 1 and c.imu_t[j] < c.mag_t[c.mag_i]:
        j += 1
    att.dcm_into((c.q[j, 0], c.q[j, 1], c.q[j, 2], c.q[j, 3]), cnb)
    m_b = c.mag_f[c.mag_i].copy()
    m_n = cnb @ m_b
    dip = np.arctan2(-m_n[2], np.hypot(m_n[0], m_n[1]))
    norm = np.sqrt(np.sum(m_b**2))
    args = (m_b, cnb, prm.mag_decl, prm.mag_sigma)
    if (
        abs(norm / prm.mag_ref - 1.0) > prm.mag_norm_gate
        or abs(dip - prm.mag_dip) > prm.mag_dip_gate
    ):
        return GATED, args
    return ON, args


# apply and factors have the shape of the other measurements' on purpose: numba takes no kernel
# as an argument without losing its disk cache, so each measurement calls its own model itself
@kernel
def apply(c: Context, x: Array, P: Array, tally: Tally, kind: int, event: int) -> None:
    """The update (counted under kind), or the disturbed field counted (event), as
    :func:`inputs_k` says."""
    verdict, args = inputs_k(c)
    if verdict == GATED:
        tally.counts[event] += 1
    elif verdict == ON:
        r, H, R = magnetic_heading_k(c.s, c.L, *args)
        update(kind, r, H, R, x, P, c.prm.chi2, tally)


def factors(c: Context) -> list[Factor]:
    """The update :func:`apply` makes at this context, as a model of the state."""
    verdict, args = inputs_k(c)
    return [factor(KINDS[0], magnetic_heading_k, *args)] if verdict == ON else []
