"""A vendor's pipe tally located on a smoothed run: every tally row (weld or feature) gets the
run's chainage, WGS84 position and sigmas.

1. The tally's weld sequence (vendor log distances, m) is matched to the run's detected welds
   by their joint lengths (:func:`.joints.align_sequences`: tolerant to missed and extra welds on
   either side and to the vendor odometer's scale error).
2. Vendor log distance -> run chainage: piecewise linear through the matched welds (so each
   joint has its own scale: wheel slip of either odometer stays local), extended beyond the
   first and last match with the least-squares scale of all matches.
3. A feature's log distance is its upstream weld's plus its distance from it; its chainage is
   that log distance mapped; its position is the centreline's at that chainage (on the pipe
   axis; the clock position stays in the tally's own columns).

Sigmas: the chainage's, from the nearest matched weld's ``sigma_distance`` and the vendor's
relative distance (``TALLY_SIGMA_M`` + ``TALLY_SIGMA_REL`` of the distance from that weld; an
unmatched stretch adds the residual scatter of the matches), projected on the pipe axis and
added to the centreline's sigma_enu there: ``sigma_h`` = horizontal, ``sigma_v`` = vertical.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.geo.attitude import body_x_axis
from pipe_nav_core.io.centreline import interpolate_trajectory
from pipe_nav_core.io.tally_csv import Tally, TallyRow
from pipe_nav_core.products.joints import align_sequences
from pipe_nav_core.products.welds import Weld
from pipe_nav_core.types import Trajectory

FloatArray = NDArray[np.float64]

TALLY_SIGMA_M = 0.02  # m, the vendor's error of a distance from a weld
TALLY_SIGMA_REL = 0.001  # of that distance (the vendor's local scale after the weld match)
MIN_MATCHES = 3  # fewer matched welds: the tally cannot be placed
MIN_MATCH_SHARE = 0.5  # nor with fewer than this share of the shorter weld list matched


@dataclass
class LocatedRow:
    """A tally row on the run: chainage m, lat/lon rad, alt m, sigma_h/sigma_v m one-sigma,
    t s (passage), matched_weld: the run weld (number) its weld or upstream weld matched, None
    when that weld matched none."""

    row: TallyRow
    distance: float
    lat: float
    lon: float
    alt: float
    sigma_h: float
    sigma_v: float
    t: float
    matched_weld: int | None


@dataclass
class TallyLocation:
    """The tally located: rows in tally order, the matched (tally weld row, run weld) pairs,
    the overall scale and offset (run chainage = scale x log distance + offset) and notes."""

    rows: list[LocatedRow]
    pairs: list[tuple[TallyRow, Weld]]
    scale: float
    offset: float
    notes: list[str] = field(default_factory=list)


def locate_tally(
    tally: Tally,
    welds: Sequence[Weld],
    centreline: Trajectory,
    *,
    scale_tolerance: float = 0.01,
    length_sigma: float = 0.1,
) -> TallyLocation:
    """Locate every row of ``tally`` on the run given by its detected ``welds`` and its
    ``centreline`` (with distance_m; sigma_enu if known) (module doc). scale_tolerance: the
    vendor odometer's scale error to allow (relative); length_sigma: m, a joint length's
    error. ValueError when fewer than MIN_MATCHES welds, or MIN_MATCH_SHARE of the shorter
    list, match."""
    tw = tally.welds()
    run = sorted(welds, key=lambda w: w.distance)
    if len(run) < MIN_MATCHES:
        raise ValueError(f"{tally.path}: the run has {len(run)} welds: nothing to match the "
                         "tally to")  # fmt: skip
    x_t = np.array([r.log for r in tw])
    x_r = np.array([w.distance for w in run])
    pairs = align_sequences(x_r, x_t, scale_tolerance=scale_tolerance, length_sigma=length_sigma)
    if len(pairs) < max(MIN_MATCHES, MIN_MATCH_SHARE * min(len(tw), len(run))):
        raise ValueError(f"{tally.path}: only {len(pairs)} of its {len(tw)} welds match the "
                         f"run's {len(run)} by joint length: not the same pipe, or another "
                         "stretch of it")  # fmt: skip
    ir, it = (np.array(v) for v in zip(*pairs, strict=True))
    xt_m, xr_m = x_t[it], x_r[ir]
    scale, offset = (float(v) for v in np.polyfit(xt_m, xr_m, 1))
    scatter = float(np.std(xr_m - (scale * xt_m + offset))) if len(pairs) > 2 else 0.0
    matched = {id(tw[j]): run[i] for i, j in pairs}
    by_number = {r.number: r for r in tw if r.number is not None}
    notes = [f"{len(pairs)} of the tally's {len(tw)} welds matched {len(run)} run welds; vendor "
             f"scale {scale:.5f} ({(scale - 1) * 100:+.3f} %)"]  # fmt: skip

    logs, ups = [], []
    for r in tally.rows:
        up = r if r.weld else (by_number.get(r.number) if r.number is not None else None)
        log = r.log if math.isfinite(r.log) else up.log + r.rel  # type: ignore[union-attr]
        logs.append(log)
        ups.append(up if up is not None else _upstream(tw, log))
    logs_a = np.array(logs)
    dist = _map(logs_a, xt_m, xr_m, scale)
    # chainage sigma: the nearest matched weld's, the vendor's relative distance, the scatter
    k = np.clip(np.searchsorted(xt_m, logs_a), 0, len(xt_m) - 1)
    k_lo = np.clip(k - 1, 0, len(xt_m) - 1)
    near = np.where(np.abs(xt_m[k_lo] - logs_a) < np.abs(xt_m[k] - logs_a), k_lo, k)
    gap = np.abs(logs_a - xt_m[near])
    node = np.array([run[ir[j]].sigma_distance for j in near])
    node = np.where(np.isfinite(node), node, 0.0)
    unmatched = np.array([id(u) not in matched for u in ups])
    sig_d = np.sqrt(node**2 + (TALLY_SIGMA_M + TALLY_SIGMA_REL * gap) ** 2
                    + np.where(unmatched, scatter, 0.0) ** 2)  # fmt: skip
    t_c = np.asarray(centreline.t, dtype=np.float64)
    d_c = np.maximum.accumulate(np.asarray(centreline.distance, dtype=np.float64))
    outside = (dist < d_c[0] - 1.0) | (dist > d_c[-1] + 1.0)
    if outside.any():
        notes.append(f"{int(outside.sum())} tally row(s) fall outside the run's chainage "
                     f"{d_c[0]:.1f}-{d_c[-1]:.1f} m: placed at its nearest end")  # fmt: skip
    t = np.interp(dist, d_c, t_c)
    at = interpolate_trajectory(centreline, t)
    n = len(t)
    sig = np.zeros((n, 3)) if at.sigma_enu is None else np.asarray(at.sigma_enu).reshape(n, 3)
    sig = np.nan_to_num(sig.astype(np.float64))
    axis = body_x_axis(at.quat_nb)
    horiz = np.hypot(axis[:, 0], axis[:, 1])
    sigma_h = np.sqrt(sig[:, 0] ** 2 + sig[:, 1] ** 2 + (sig_d * horiz) ** 2)
    sigma_v = np.sqrt(sig[:, 2] ** 2 + (sig_d * axis[:, 2]) ** 2)
    rows = [
        LocatedRow(
            r,
            float(dist[m]),
            float(at.lat[m]),
            float(at.lon[m]),
            float(at.h[m]),
            float(sigma_h[m]),
            float(sigma_v[m]),
            float(t[m]),
            matched[id(ups[m])].number if id(ups[m]) in matched else None,
        )  # fmt: skip
        for m, r in enumerate(tally.rows)
    ]
    return TallyLocation(rows, [(tw[j], run[i]) for i, j in pairs], scale, offset, notes)


def _upstream(welds: list[TallyRow], log: float) -> TallyRow:
    """The last tally weld at or before log distance ``log`` (the first weld if none)."""
    k = int(np.searchsorted([w.log for w in welds], log, side="right")) - 1
    return welds[max(k, 0)]


def _map(x: FloatArray, xt: FloatArray, xr: FloatArray, scale: float) -> FloatArray:
    """Log distances -> run chainage: piecewise linear through the matches (xt -> xr), the
    overall ``scale`` beyond them."""
    out = np.interp(x, xt, xr)
    lo, hi = x < xt[0], x > xt[-1]
    out[lo] = xr[0] + scale * (x[lo] - xt[0])
    out[hi] = xr[-1] + scale * (x[hi] - xt[-1])
    return out


__all__ = ["LocatedRow", "TallyLocation", "locate_tally"]
