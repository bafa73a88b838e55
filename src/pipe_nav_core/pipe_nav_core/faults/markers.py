"""Markers that disagree with the rest of the run: found, left out, named.

A marker surveyed metres off, or whose passage was stamped seconds late, is not rejected by the
forward filter when it anchors the heading or the odometer scale: the smoothed run then bends
to fit it (tens of metres off, a scale factor of 0.8) and another, good marker is the one that
no longer fits. So the test has two steps:

1. screening, free: each marker's smoothed residual (position minus survey, ENU m) against its
   residual covariance R - P (R: the survey sigmas plus the passage-time sigma times the
   odometer speed along the axis; P: the smoothed position covariance there), and whether the
   filter had to inflate its covariance at the marker's passage (it disagreed beyond the
   gate: the smoother may then fit it, a small residual on a wrong run). A clean run ends
   here.
2. when a marker fails it, leave-one-out: the run is smoothed without each suspect in turn (the
   failing markers and their neighbours, :func:`suspects`) and that marker's position
   predicted by the others is tested against R + P; of those over the
   chi-square bound whose removal makes all the others pass the screening, the one leaving
   them most consistent is left out, and the test repeats on the run without it. When no
   single removal makes the others agree, the fault is not a marker (the IMU or odometer
   model, a bad segment): nothing is left out and the result's summary names the
   disagreement (``marker_disagreement``): its sigmas do not cover its error.

The result is then the run without the outlier, exactly, and the marker is named with its
leave-one-out residual. With fewer than three markers an outlier cannot be told from the
others: the odometer scale the markers imply is then checked against its prior instead.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from pipe_nav_core.app.progress import QUIET, Progress
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.kalman import chi2_threshold
from pipe_nav_core.geo.attitude import body_x_axis
from pipe_nav_core.smooth.centreline import SmoothResult, marker_residuals
from pipe_nav_core.types import Marker, SensorLog

OUTLIER_PROBABILITY = 1.0 - 1e-6  # chi-square (3 dof) bound on a marker's normalized residual
MIN_MARKERS = 3  # fewer cannot tell an outlier from the others
MAX_FAILING = 3  # more markers failing the screening at once: not one outlier (no leave-one-out)
# a wrong marker bends the smoothed run about itself and its neighbours (each marker pins the
# run): the markers left out in turn are those failing the screening and this many on each side
# of each, in passage order (every marker on a short run; a handful on a 100 km line)
NEIGHBOURS = 2


@dataclass(frozen=True)
class MarkerOutlier:
    """A marker left out: name; residual (3,) ENU m against the solution of the others;
    sigma_m: one-sigma of that residual along it (survey, timing, the others' solution), m;
    nis: its normalized squared residual."""

    name: str
    residual: np.ndarray
    sigma_m: float
    nis: float

    def describe(self) -> str:
        r = float(np.linalg.norm(self.residual))
        return (
            f"marker {self.name} left out: {r:.2f} m from the solution of the other markers "
            f"(sigma {self.sigma_m:.3f} m)"
        )


def marker_covariance(
    result: SmoothResult, log: SensorLog, marker: Marker, config: NavConfig
) -> np.ndarray:
    """(3, 3) ENU m^2: the survey sigmas plus the passage-time sigma times the odometer speed
    along the smoothed axis (the smoothed velocity itself bends when a marker is wrong)."""
    c = result.centreline
    i = int(np.clip(np.searchsorted(c.t, marker.t), 0, len(c.t) - 1))
    axis = body_x_axis(c.quat_nb[i])
    odo = log.odometer
    speed = float(np.interp(marker.t, odo.t, odo.speed)) if len(odo.t) else 0.0
    v = speed * axis
    cov = np.diag(np.square(np.asarray(marker.sigma_enu, dtype=np.float64)))
    return cov + config.marker_time_sigma**2 * np.outer(v, v)


def _position_cov(result: SmoothResult, t: float) -> np.ndarray:
    c = result.centreline
    if c.sigma_enu is None:
        return np.zeros((3, 3))
    i = int(np.clip(np.searchsorted(c.t, t), 0, len(c.t) - 1))
    return np.diag(np.square(np.asarray(c.sigma_enu[i], dtype=np.float64)))


def _nis(r: np.ndarray, cov: np.ndarray, floor: float) -> float:
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    w = np.maximum(w, floor)
    return float(r @ ((v / w) @ v.T) @ r)


# R - P is approximate (P from the centreline's sigmas about the passage, without their
# correlations): where it comes out near zero or negative in some direction, it is taken as
# this share of R there. Without it a clean 100 km line failed the screening at a marker whose
# P came out above its R (nis 307), and the leave-one-out smoothed the run again and again.
SCREEN_FLOOR = 0.1


def _screened_nis(r: np.ndarray, R: np.ndarray, P: np.ndarray) -> float:
    """r^T (R - P)^-1 r with R - P no smaller than SCREEN_FLOOR R in any direction."""
    w, v = np.linalg.eigh(0.5 * (R + R.T))
    root = (v / np.sqrt(np.maximum(w, 1e-30))) @ v.T  # R^(-1/2)
    a, u = np.linalg.eigh(root @ (R - P) @ root)
    z = u.T @ (root @ r)
    return float(np.sum(z * z / np.maximum(a, SCREEN_FLOOR)))


def screening(
    result: SmoothResult, log: SensorLog, config: NavConfig, *, floor: bool = True
) -> dict[str, float]:
    """name -> each marker's smoothed residual normalized by R - P (step 1 of the module),
    R - P floored at SCREEN_FLOOR R (``floor=False``: only at a hundredth of R's smallest
    eigenvalue: sharper, which ranks the candidates of step 2 better, but a clean run with
    many markers can fail it)."""
    res = marker_residuals(result.centreline, result.markers)
    out: dict[str, float] = {}
    for m in result.markers:
        if m.name in res:
            R = marker_covariance(result, log, m, config)
            P = _position_cov(result, m.t)
            if not (np.isfinite(res[m.name]).all() and np.isfinite(P).all()):
                out[m.name] = math.inf  # a run that diverged there: no test, it fails
            elif floor:
                out[m.name] = _screened_nis(res[m.name], R, P)
            else:
                out[m.name] = _nis(res[m.name], R - P, 0.01 * float(np.linalg.eigvalsh(R)[0]))
    return out


def smooth_without_outliers(
    log: SensorLog,
    config: NavConfig,
    smooth: Callable[[SensorLog], SmoothResult],
    progress: Progress = QUIET,
) -> tuple[SmoothResult, list[MarkerOutlier], list[str]]:
    """``smooth(log)``, and again without each marker that fails the test of the module (while
    at least three are left); returns the result, the markers left out and warnings.
    ``progress`` is told when the leave-one-out starts and what it leaves out (``smooth``
    tells it of its own passes)."""
    bound = chi2_threshold(OUTLIER_PROBABILITY, 3)
    result = smooth(log)
    outliers: list[MarkerOutlier] = []
    while len(log.markers) >= MIN_MARKERS:
        screen = screening(result, log, config)
        failing = sum(v > bound for v in screen.values())
        # a marker the filter had to inflate its covariance for disagreed with the run: the
        # smoother, given that freedom, can fit it (a passage stamped 3 s late on the 3 km
        # line, 2 cm off its survey, the run 6.5 m off), so it is a suspect whatever its residual
        named = result.summary.get("markers_inflated") or ()
        inflated = set(named) & screen.keys()  # type: ignore[call-overload]
        if not failing and not inflated:
            break
        best: tuple[float, MarkerOutlier, SmoothResult, SensorLog] | None = None
        if failing <= MAX_FAILING:
            progress.stage("a marker disagrees with the others: testing each against the rest")
        # the marker whose removal leaves the others most consistent, if it fails against them
        flagged = {k: math.inf if k in inflated else v for k, v in screen.items()}
        for m in suspects(log.markers, flagged, bound) if failing <= MAX_FAILING else ():
            if m.name not in screen:
                continue
            rest = replace(log, markers=[x for x in log.markers if x.name != m.name])
            without = smooth(rest)
            r = marker_residuals(without.centreline, [m]).get(m.name)
            if r is None or not np.isfinite(r).all():
                continue
            cov = marker_covariance(without, log, m, config) + _position_cov(without, m.t)
            value = _nis(r, cov, 1e-12)
            if value <= bound:
                continue
            if max(screening(without, rest, config).values(), default=0.0) > bound:
                continue  # the others still disagree: not this marker alone
            misfit = max(screening(without, rest, config, floor=False).values(), default=0.0)
            if best is None or misfit < best[0]:
                along = r / max(float(np.linalg.norm(r)), 1e-12)
                sigma = math.sqrt(float(along @ cov @ along))
                best = (misfit, MarkerOutlier(m.name, r, sigma, value), without, rest)
        if best is None:
            if not failing:  # inflated only: its sigmas widened there, no marker to blame
                break
            disagree = sorted(k for k, v in screen.items() if v > bound)
            why = ("leaving out any one does not make the others agree" if failing <= MAX_FAILING
                   else "too many for one wrong marker")  # fmt: skip
            result.summary["marker_disagreement"] = (
                f"marker(s) {', '.join(disagree)} disagree with the smoothed run beyond their "
                f"sigmas ({why})"
            )
            break
        outliers.append(best[1])
        result, log = best[2], best[3]
        progress.stage(best[1].describe())
    warnings = [o.describe() for o in outliers]
    if len(log.markers) < MIN_MARKERS:
        warnings += _scale_check(result, config)
    return result, outliers, warnings


def suspects(markers: list[Marker], screen: dict[str, float], bound: float) -> list[Marker]:
    """The markers that may be the wrong one (step 2 of the module): each marker whose
    screening value (``screen``: name -> normalized residual) is over ``bound``, and its
    NEIGHBOURS on either side in passage order; in the order of ``markers``."""
    order = sorted(range(len(markers)), key=lambda i: markers[i].t)
    rank = {markers[i].name: k for k, i in enumerate(order)}
    keep: set[int] = set()
    for name, value in screen.items():
        if value > bound and name in rank:
            k = rank[name]
            keep.update(order[max(0, k - NEIGHBOURS) : k + NEIGHBOURS + 1])
    return [m for i, m in enumerate(markers) if i in keep]


def _scale_check(result: SmoothResult, config: NavConfig) -> list[str]:
    """With too few markers to vote: the odometer scale they imply against its prior."""
    scale = float(result.summary.get("odometer_scale", 1.0))  # type: ignore[arg-type]
    bound = 3.0 * config.odometer_scale_sigma
    if math.isfinite(scale) and abs(scale - 1.0) > bound:
        return [
            f"the markers imply an odometer scale of {scale:.4f}, beyond 3 sigma of its prior "
            f"({config.odometer_scale_sigma:g}): a marker may be wrong, which {len(result.markers)}"
            " markers cannot tell"
        ]
    return []
