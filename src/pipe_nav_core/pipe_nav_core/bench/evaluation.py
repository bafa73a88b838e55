"""Scoring an estimated trajectory against the truth.

Errors are compared by TIME: the truth is interpolated (linearly, in a local ENU frame about a
datum) at the estimate's stamps, and the estimate minus the truth is split into horizontal
(hypot of east and north) and vertical (|up|) errors, in metres. Between markers the error is also
expressed as the surveyors' 1:N figure, N = marker spacing / largest horizontal error between the
first and the last marker.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.geo import earth
from pipe_nav_core.types import Datum, Marker, Trajectory

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Score:
    """Accuracy figures of one estimate (metres unless stated).

    max_h, rms_h: horizontal error (hypot east, north); max_v, rms_v: vertical error |up|;
    max_h_between_markers: largest horizontal error of the samples from the first to the last
    marker passage; ratio_between_markers: N of the 1:N figure, marker_spacing /
    max_h_between_markers (dimensionless; inf for a zero error); inside_3sigma: fraction of the
    samples whose horizontal error is within 3 sqrt(sigma_e^2 + sigma_n^2) and whose vertical
    error is within 3 sigma_u (Trajectory.sigma_enu; nan without sigmas); n: samples compared.
    Also: max_v_between_markers, marker_spacing (median spacing of the markers' true chainages),
    max_3d (largest 3-D error); sigma_h_at_max_h, sigma_v_at_max_v: the estimate's own
    horizontal (sqrt(sigma_e^2 + sigma_n^2)) and vertical one-sigma at the sample of its
    largest horizontal and vertical error (nan without sigmas): whether the estimator
    expected an error of that size there.
    """

    max_h: float
    rms_h: float
    max_v: float
    rms_v: float
    max_h_between_markers: float
    ratio_between_markers: float
    inside_3sigma: float
    n: int
    max_v_between_markers: float = math.nan
    marker_spacing: float = math.nan
    max_3d: float = math.nan
    sigma_h_at_max_h: float = math.nan
    sigma_v_at_max_v: float = math.nan

    def summary(self) -> str:
        """One line for logs and reports (cm and 1:N)."""
        ratio = (
            f"1:{self.ratio_between_markers:.0f}"
            if math.isfinite(self.ratio_between_markers)
            else "n/a"
        )
        return (
            f"n={self.n} max_h={100 * self.max_h:.1f} cm rms_h={100 * self.rms_h:.1f} cm "
            f"max_v={100 * self.max_v:.1f} cm rms_v={100 * self.rms_v:.1f} cm "
            f"between markers max_h={100 * self.max_h_between_markers:.1f} cm ({ratio}) "
            f"inside 3 sigma={self.inside_3sigma:.3f}"
        )


def trajectory_enu(traj: Trajectory, datum: Datum) -> FloatArray:
    """Positions of ``traj`` in the ENU frame of ``datum`` (map), shape (N, 3), m."""
    lat, lon, h = (np.asarray(x, dtype=np.float64) for x in (traj.lat, traj.lon, traj.h))
    return earth.geodetic_to_enu(lat, lon, h, datum.lat, datum.lon, datum.alt).reshape(-1, 3)


def _datum_of(truth: Trajectory) -> Datum:
    return Datum(float(truth.lat[0]), float(truth.lon[0]), float(truth.h[0]))


def _strictly_increasing(t: FloatArray, enu: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Drop samples whose stamp does not increase (keeps the first of equal stamps)."""
    keep = np.concatenate([[True], np.diff(t) > 0.0])
    if np.all(keep):
        return t, enu
    # Non-monotone truth: sort, then drop repeats.
    order = np.argsort(t, kind="stable")
    t, enu = t[order], enu[order]
    keep = np.concatenate([[True], np.diff(t) > 0.0])
    return t[keep], enu[keep]


def errors_enu(
    estimate: Trajectory, truth: Trajectory, *, datum: Datum | None = None
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Estimate-minus-truth position errors in ENU (m) at the estimate's stamps.

    The truth is linearly interpolated at ``estimate.t`` in the ENU frame of ``datum`` (default:
    the truth's first sample). Returns (t s, errors (N, 3) m, mask of the samples inside the
    truth's time span); errors outside the span are nan.
    """
    if len(truth) < 2:
        raise ValueError("the truth needs at least two samples")
    d = datum if datum is not None else _datum_of(truth)
    tt, te = _strictly_increasing(np.asarray(truth.t, dtype=np.float64), trajectory_enu(truth, d))
    t = np.asarray(estimate.t, dtype=np.float64)
    inside = (t >= tt[0]) & (t <= tt[-1]) & np.isfinite(t)
    ref = np.stack([np.interp(t, tt, te[:, k]) for k in range(3)], axis=-1)
    err = trajectory_enu(estimate, d) - ref
    err[~inside] = np.nan
    return t, err, inside


def score(
    estimate: Trajectory,
    truth: Trajectory,
    markers: Sequence[Marker] | None = None,
    *,
    datum: Datum | None = None,
) -> Score:
    """Score ``estimate`` against ``truth`` by time (see the module docstring).

    markers: the run's markers (their passage times delimit "between markers"; their chainages
    are the truth's distance at those times). datum: ENU origin (default: the truth's first
    sample; the choice changes nothing but the ENU curvature far from it). Estimate samples
    outside the truth's time span, or with non-finite positions, are ignored.
    """
    t, err, inside = errors_enu(estimate, truth, datum=datum)
    ok = inside & np.all(np.isfinite(err), axis=1)
    n = int(np.count_nonzero(ok))
    nan = math.nan
    if n == 0:
        return Score(nan, nan, nan, nan, nan, nan, nan, 0)
    e = err[ok]
    eh = np.hypot(e[:, 0], e[:, 1])
    ev = np.abs(e[:, 2])
    e3 = np.linalg.norm(e, axis=1)

    inside3 = sigma_h_at = sigma_v_at = nan
    if estimate.sigma_enu is not None:
        sig = np.asarray(estimate.sigma_enu, dtype=np.float64).reshape(-1, 3)[ok]
        sh = np.hypot(sig[:, 0], sig[:, 1])
        good = (eh <= 3.0 * sh) & (ev <= 3.0 * sig[:, 2])
        inside3 = float(np.mean(good))
        sigma_h_at = float(sh[np.argmax(eh)])
        sigma_v_at = float(sig[np.argmax(ev), 2])

    max_hb = max_vb = spacing = ratio = nan
    if markers:
        ms = sorted(markers, key=lambda m: m.t)
        mt = np.array([m.t for m in ms], dtype=np.float64)
        tt = np.asarray(truth.t, dtype=np.float64)
        chain = np.interp(mt, tt, np.asarray(truth.distance, dtype=np.float64))
        if len(chain) >= 2:
            spacing = float(np.median(np.diff(chain)))
        tk = t[ok]
        between = (tk >= mt[0]) & (tk <= mt[-1])
        if len(ms) >= 2 and np.any(between):
            max_hb = float(np.max(eh[between]))
            max_vb = float(np.max(ev[between]))
            if math.isfinite(spacing):
                ratio = spacing / max_hb if max_hb > 0.0 else math.inf
    return Score(
        max_h=float(np.max(eh)),
        rms_h=float(np.sqrt(np.mean(eh * eh))),
        max_v=float(np.max(ev)),
        rms_v=float(np.sqrt(np.mean(ev * ev))),
        max_h_between_markers=max_hb,
        ratio_between_markers=ratio,
        inside_3sigma=inside3,
        n=n,
        max_v_between_markers=max_vb,
        marker_spacing=spacing,
        max_3d=float(np.max(e3)),
        sigma_h_at_max_h=sigma_h_at,
        sigma_v_at_max_v=sigma_v_at,
    )


def profile_sag_depth(points: FloatArray) -> float:
    """Sag depth of a profile (m): the largest drop of the points below the straight line
    joining the first and the last point, measured vertically at the same position along the
    horizontal chord. points: (N, 3) rows (east m, north m, height m) in order along the pipe.
    Zero when no point lies below the line (a hump or a straight pipe)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3:
        raise ValueError("a sag depth needs at least three points")
    chord = p[-1, :2] - p[0, :2]
    length = float(np.hypot(chord[0], chord[1]))
    if length <= 0.0:
        raise ValueError("the profile's ends coincide horizontally")
    lam = ((p[:, :2] - p[0, :2]) @ chord) / (length * length)
    line = p[0, 2] + lam * (p[-1, 2] - p[0, 2])
    return float(np.max(line - p[:, 2]))


def sag_depth(
    traj: Trajectory,
    *,
    start: float | None = None,
    end: float | None = None,
    datum: Datum | None = None,
) -> float:
    """Sag depth (m) of a trajectory's profile: lowest point relative to the straight line
    between the pipe ends (seed 000's 20 cm / 41.5 cm sags).

    The profile is ellipsoidal height h versus horizontal position (east, north in the ENU frame
    of ``datum``, default the first sample), so a level pipe has no sag whatever its length.
    start, end: chainage limits (m, on ``traj.distance``) of the stretch to examine (default:
    the whole trajectory; the rest periods at the ends do no harm).
    """
    d = datum if datum is not None else _datum_of(traj)
    pts = trajectory_enu(traj, d)
    pts[:, 2] = np.asarray(traj.h, dtype=np.float64)
    dist = np.asarray(traj.distance, dtype=np.float64)
    sel = np.ones(len(dist), dtype=bool)
    if start is not None:
        sel &= dist >= start
    if end is not None:
        sel &= dist <= end
    return profile_sag_depth(pts[sel])
