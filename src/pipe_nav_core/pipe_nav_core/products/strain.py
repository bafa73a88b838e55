"""Bending strain along the pipe and the strain features over thresholds.

Bending strain at the outer fibre is curvature x outer diameter / 2 (a thin-walled pipe bent
elastically); it is reported in percent, as integrity engineers read it. A strain feature is a
stretch where the strain exceeds a threshold (``strain_thresholds``): its peak, length and
plane, the listed bend that explains it (an as-built bend overlapping it), and, when a
reference of as-built bends is given (``--bends-reference``), whether it lies outside every
one of them (not construction-related: ground movement, a free span, a dent).
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.model.sensors import ImuSpec
from pipe_nav_core.products.bends import PipeBend
from pipe_nav_core.products.curvature import AxisTrack, CurvatureProfile, windowed_curvature

FloatArray = NDArray[np.float64]


def strain_pct(profile: CurvatureProfile, outer_diameter: float) -> tuple[FloatArray, FloatArray]:
    """(strain, sigma) in percent at each profile row, for an outer diameter in m."""
    k = 0.5 * outer_diameter * 100.0
    return profile.total * k, profile.sigma * k


@dataclass(frozen=True)
class StrainFeature:
    """A stretch over one strain threshold. Chainages m of distance_m; lat, lon rad and alt m
    at the peak; peak_pct and sigma_peak_pct percent; plane rad (as the curvature's plane);
    threshold_pct percent; bend: number of the listed bend overlapping it, or 0;
    construction: True inside a reference bend, False outside all, None without a reference."""

    number: int
    threshold_pct: float
    start_m: float
    peak_m: float
    end_m: float
    lat: float
    lon: float
    alt: float
    peak_pct: float
    sigma_peak_pct: float
    plane: float
    bend: int
    construction: bool | None

    @property
    def length_m(self) -> float:
        return self.end_m - self.start_m


def read_bends_reference(path: str | os.PathLike[str]) -> list[tuple[float, float]]:
    """Chainage intervals (m) of as-built bends from a CSV with columns ``start_m,end_m``
    (further columns ignored); ValueError naming the file and line when malformed."""
    out: list[tuple[float, float]] = []
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = csv.DictReader(f)
            missing = {"start_m", "end_m"} - set(rows.fieldnames or [])
            if missing:
                raise ValueError(f"{path}: the header lacks {', '.join(sorted(missing))}")
            for line, row in enumerate(rows, start=2):
                try:
                    a, b = float(row["start_m"]), float(row["end_m"])
                except (TypeError, ValueError):
                    raise ValueError(f"{path}:{line}: start_m and end_m must be numbers") from None
                if not (math.isfinite(a) and math.isfinite(b) and a <= b):
                    raise ValueError(f"{path}:{line}: need finite start_m <= end_m")
                out.append((a, b))
    except OSError as exc:
        raise ValueError(f"{path}: {exc.strerror or exc}") from None
    return out


def strain_features(
    profile: CurvatureProfile,
    outer_diameter: float,
    thresholds: Sequence[float],
    bends: Sequence[PipeBend] = (),
    reference: Sequence[tuple[float, float]] | None = None,
    track: AxisTrack | None = None,
    spec: ImuSpec | None = None,
) -> list[StrainFeature]:
    """Every stretch over each threshold (percent), in chainage order then threshold; stretches
    apart by less than a window are one. With the profile's ``track`` and ``spec`` each peak
    is taken on a grid of an eighth of the window (the rows may straddle a short peak), and the
    stretch reaches it (start_m <= peak_m <= end_m)."""
    strain, sigma = strain_pct(profile, outer_diameter)
    d = profile.distance
    stretches: list[tuple[float, int, int, int]] = []  # threshold, first and last row, peak row
    for thr in sorted(thresholds):
        over = strain > thr
        edges = np.flatnonzero(np.diff(np.concatenate([[0], over.astype(np.int8), [0]])))
        runs = list(zip(edges[::2], edges[1::2] - 1, strict=True))
        merged: list[tuple[int, int]] = []
        for a, b in runs:
            if merged and d[a] - d[merged[-1][1]] <= profile.window:
                merged[-1] = (merged[-1][0], b)
            else:
                merged.append((a, b))
        stretches += [(thr, a, b, a + int(np.argmax(strain[a : b + 1]))) for a, b in merged]
    peaks: list[tuple[float, ...] | None] = [None] * len(stretches)
    if track and spec and stretches:
        peaks = list(_peaks(profile, outer_diameter, track, spec, [s[3] for s in stretches]))
    found: list[StrainFeature] = []
    for (thr, a, b, i), peak in zip(stretches, peaks, strict=True):
        start, end = float(d[a]), float(d[b])
        if peak is not None:  # over the threshold there too: a stretch of one row or two
            start, end = min(start, peak[0]), max(end, peak[0])  # reaches its peak
        bend = next((x.number for x in bends if x.start_m <= end and start <= x.end_m), 0)
        construction = (
            None if reference is None else any(r0 <= end and start <= r1 for r0, r1 in reference)
        )
        if peak is None:
            peak = (float(d[i]), float(profile.lat[i]), float(profile.lon[i]),
                    float(profile.alt[i]), float(strain[i]), float(sigma[i]),
                    float(profile.plane[i]))  # fmt: skip
        found.append(StrainFeature(0, float(thr), start, peak[0], end, *peak[1:], bend,
                                   construction))  # fmt: skip
    found.sort(key=lambda f: (f.start_m, f.threshold_pct))
    return [replace(f, number=n + 1) for n, f in enumerate(found)]


def _peaks(
    profile: CurvatureProfile,
    outer_diameter: float,
    track: AxisTrack,
    spec: ImuSpec,
    rows: list[int],
) -> list[tuple[float, ...]]:
    """(chainage m, lat, lon rad, alt m, strain %, sigma %, plane rad) of the peak near each
    of ``rows``, on a grid of an eighth of the window within a window of it (every row's grid
    in one call of windowed_curvature: a call a row would be mostly numpy's overhead)."""
    w = profile.window
    centres = track.arc_at(profile.distance[np.asarray(rows, dtype=np.int64)]).tolist()
    grids = [np.arange(c - w, c + w + 1e-9, w / 8.0) for c in centres]
    arcs = np.concatenate(grids)
    v = windowed_curvature(track, arcs, w, spec)
    first = np.cumsum([0] + [len(g) for g in grids[:-1]])
    at = np.array([f + int(np.argmax(v["total"][f : f + len(g)]))
                   for f, g in zip(first, grids, strict=True)], dtype=np.int64)  # fmt: skip
    arc = arcs[at]
    k = 0.5 * outer_diameter * 100.0
    lat, lon, alt = track.position_at(arc)
    return list(zip(track.distance_at(arc).tolist(), lat.tolist(), lon.tolist(), alt.tolist(),
                    (v["total"][at] * k).tolist(), (v["sigma"][at] * k).tolist(),
                    v["plane"][at].tolist(), strict=True))  # fmt: skip
