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
    found: list[StrainFeature] = []
    d = profile.distance
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
        for a, b in merged:
            i = a + int(np.argmax(strain[a : b + 1]))
            start, end = float(d[a]), float(d[b])
            peak = _peak(profile, outer_diameter, track, spec, i) if track and spec else None
            if peak is not None:  # over the threshold there too: a stretch of one row or two
                start, end = min(start, peak[0]), max(end, peak[0])  # reaches its peak
            bend = next((x.number for x in bends if x.start_m <= end and start <= x.end_m), 0)
            construction = (
                None
                if reference is None
                else any(r0 <= end and start <= r1 for r0, r1 in reference)
            )
            if peak is None:
                peak = (float(d[i]), float(profile.lat[i]), float(profile.lon[i]),
                        float(profile.alt[i]), float(strain[i]), float(sigma[i]),
                        float(profile.plane[i]))  # fmt: skip
            found.append(StrainFeature(0, float(thr), start, peak[0], end, *peak[1:], bend,
                                       construction))  # fmt: skip
    found.sort(key=lambda f: (f.start_m, f.threshold_pct))
    return [replace(f, number=n + 1) for n, f in enumerate(found)]


def _peak(
    profile: CurvatureProfile, outer_diameter: float, track: AxisTrack, spec: ImuSpec, i: int
) -> tuple[float, ...]:
    """(chainage m, lat, lon rad, alt m, strain %, sigma %, plane rad) of the peak near row i,
    on a grid of an eighth of the window within a window of it."""
    w = profile.window
    centre = float(track.arc_at(np.array([profile.distance[i]]))[0])
    arc = np.arange(centre - w, centre + w + 1e-9, w / 8.0)
    v = windowed_curvature(track, arc, w, spec)
    j = int(np.argmax(v["total"]))
    k = 0.5 * outer_diameter * 100.0
    lat, lon, alt = (float(x[0]) for x in track.position_at(arc[j : j + 1]))
    return (float(track.distance_at(arc[j : j + 1])[0]), lat, lon, alt,
            float(v["total"][j]) * k, float(v["sigma"][j]) * k, float(v["plane"][j]))  # fmt: skip
