"""Surveyed marker position versus the estimate at the passage time, ENU m.

The nominal position is extrapolated from the state's time to the passage with the current
velocity (at most one IMU interval here); the passage-time uncertainty adds speed *
marker_time_sigma along the track. Before the update, in Python between the epoch's
prediction and its updates: a passage stamped over LATE_MARKER_S before the epoch is dropped
(:func:`late`), and a filter the marker contradicts beyond the chi-square gate has its
predicted covariance inflated until it agrees (:func:`inflation`; a surveyed marker is the
ground truth, anchoring.HeadingAnchor.before_marker). The compiled update then applies each
passage of the epoch, gated as every update.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.filter.kalman import chi2_threshold
from pipe_nav_core.geo import earth
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements.context import Context, Measurement, factor, update
from pipe_nav_core.model.state import (
    I_VEL,
    L_N,
    L_POS,
    SV_H,
    SV_LAT,
    SV_LON,
    SV_T,
    Layout,
    NavState,
)
from pipe_nav_core.types import Marker

if TYPE_CHECKING:
    from pipe_nav_core.model.measurements.context import Array, Factor, Index, Model, Tally

KINDS, EVENTS = ("marker",), ()  # its update (statistics), the events it counts

LATE_MARKER_S = 2.0  # s: a marker passage this far before its epoch's start is dropped


@kernel
def marker_fix_k(sv: Array, L: Index, marker: Array, time_sigma: float) -> Model:
    """:func:`marker_fix` on a flat state; marker = [t s, lat rad, lon rad, alt m, sigma E, N,
    U m] (:func:`marker_vector`)."""
    dt = marker[0] - sv[SV_T]
    lat, h = sv[SV_LAT], sv[SV_H]
    rm, rn = earth._radii(lat)
    vel = sv[I_VEL : I_VEL + 3]
    d_enu = np.empty(3)
    d_enu[0] = (marker[2] - sv[SV_LON]) * (rn + h) * np.cos(lat) - vel[0] * dt
    d_enu[1] = (marker[1] - lat) * (rm + h) - vel[1] * dt
    d_enu[2] = marker[3] - h - vel[2] * dt
    H = np.zeros((3, L[L_N]))
    for r in range(3):
        H[r, L[L_POS] + r] = 1.0
    R = np.diag(marker[4:7] ** 2) + time_sigma**2 * np.outer(vel, vel)
    return d_enu, H, R


def marker_vector(m: Marker) -> Array:
    """A marker as the flat vector marker_fix_k takes."""
    return np.array([m.t, m.lat, m.lon, m.alt, *m.sigma_enu], dtype=np.float64)


def marker_fix(s: NavState, layout: Layout, marker: Marker, *, time_sigma: float) -> Measurement:
    """The update for a NavState (time_sigma s)."""
    r, H, R = marker_fix_k(s.vector(), layout.index, marker_vector(marker), float(time_sigma))
    return Measurement("marker", r, H, R)


def late(m: Marker, t: float) -> bool:
    """Whether a passage is stamped over LATE_MARKER_S before the epoch's start t (s)."""
    return m.t < t - LATE_MARKER_S


def inflation(
    s: NavState,
    layout: Layout,
    m: Marker,
    x: Array,
    P: Array,
    *,
    time_sigma: float,
    gate_probability: float,
) -> float | None:
    """The factor by which the predicted covariance P (mean error x) must grow for the marker
    to pass the chi-square gate (its NIS per row), or None where it passes already."""
    mm = marker_fix(s, layout, m, time_sigma=time_sigma)
    r = mm.residual - mm.H @ x
    S = mm.H @ P @ mm.H.T + mm.R
    nis = float(r @ np.linalg.solve(S, r))
    limit = chi2_threshold(gate_probability, len(r))
    if np.isfinite(nis) and nis > limit:
        return nis / len(r)
    return None


@kernel
def apply(c: Context, x: Array, P: Array, tally: Tally, kind: int, event: int) -> None:
    """Each passage of the epoch (c.markers) in turn, counted under kind, its residual written
    to tally.marker_res."""
    for j in range(c.markers.shape[0]):
        r, H, R = marker_fix_k(c.s, c.L, c.markers[j], c.prm.marker_time)
        tally.marker_res[j] = r
        update(kind, r, H, R, x, P, c.prm.chi2, tally)


def factors(c: Context) -> list[Factor]:
    """The updates :func:`apply` makes at this context, as models of the state (in the order
    of c.markers)."""
    time_sigma = float(c.prm.marker_time)
    return [factor(KINDS[0], marker_fix_k, np.array(row, dtype=np.float64), time_sigma)
            for row in c.markers]  # fmt: skip
