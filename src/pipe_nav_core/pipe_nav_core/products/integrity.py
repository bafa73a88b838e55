"""The integrity products of one run, computed together from its smoothed trajectory."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.io.centreline import pieces_of
from pipe_nav_core.products.bends import PipeBend, find_bends
from pipe_nav_core.products.curvature import CurvatureProfile, axis_track, curvature_profile
from pipe_nav_core.products.strain import StrainFeature, strain_features, strain_pct
from pipe_nav_core.types import Trajectory


@dataclass(frozen=True)
class IntegrityReport:
    """Curvature profile, strain (percent, with sigma), bends and strain features of a run, and
    the settings they were computed with (outer diameter m, window m, thresholds percent)."""

    profile: CurvatureProfile
    strain_pct: NDArray[np.float64]  # (N,) percent, per profile row
    sigma_strain_pct: NDArray[np.float64]  # (N,) percent
    bends: list[PipeBend]
    features: list[StrainFeature]
    outer_diameter: float
    window: float
    thresholds_pct: tuple[float, ...]
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, object]:
        """Figures for people: counts, the largest strain (percent) and the listed bend it lies
        in (0: none), and the largest strain outside every bend (a bend made as one, an
        induction bend of 5 D, is 10 % of "strain" by its shape alone; what the pipe body
        carries is the rest). A row lies in a bend within half a curvature window of its
        ends, the stretch the window spreads the bend's curvature over."""
        strain, d = self.strain_pct, self.profile.distance
        peak, in_bend, outside = 0.0, 0, 0.0
        if len(self.profile):
            i = int(np.argmax(strain))
            peak = float(strain[i])
            half = 0.5 * self.window
            free = np.ones(len(d), dtype=bool)
            for b in self.bends:
                inside = (d >= b.start_m - half) & (d <= b.end_m + half)
                free &= ~inside
                if inside[i] and not in_bend:
                    in_bend = b.number
            outside = float(strain[free].max()) if free.any() else 0.0
        return {
            "bends": len(self.bends),
            "strain_features": len(self.features),
            "max_strain_pct": peak,
            "max_strain_bend": in_bend,
            "max_strain_outside_bends_pct": outside,
            "curvature_window_m": self.window,
            "outer_diameter_m": self.outer_diameter,
            "strain_thresholds_pct": list(self.thresholds_pct),
            "notes": list(self.notes),
        }


def integrity_report(
    traj: Trajectory,
    config: NavConfig,
    *,
    spacing: float = 0.5,
    reference: Sequence[tuple[float, float]] | None = None,
) -> IntegrityReport:
    """Curvature, strain, bends and strain features of a smoothed trajectory, with the
    settings of ``config`` (its IMU model gives the sigmas) every ``spacing`` m of chainage.
    A trajectory in pieces (segments smoothed apart across data gaps: io.centreline.pieces_of)
    gets the products of each piece, numbered on."""
    pieces = pieces_of(traj)
    if len(pieces) > 1:
        return _merged([integrity_report(p, config, spacing=spacing, reference=reference)
                        for p in pieces if len(p.t) > 1])  # fmt: skip
    spec = config.imu_spec()
    window = config.window()
    diameter = config.outer_diameter()
    track = axis_track(traj, min(0.02, window / 8.0))
    profile = curvature_profile(traj, spec, window=window, spacing=spacing, track=track)
    bends = find_bends(profile, track, spec, threshold_radius=config.bend_threshold_radius,
                       min_angle=config.bend_min_angle, outer_diameter=diameter,
                       class_limits=config.bend_class_limits)  # fmt: skip
    strain, sigma = strain_pct(profile, diameter)
    features = strain_features(profile, diameter, config.strain_thresholds, bends, reference,
                               track, spec)  # fmt: skip
    notes = []
    if not config.pipe_outer_diameter:
        notes.append(f"strain with pipe_diameter {diameter} m (pipe_outer_diameter not set)")
    return IntegrityReport(profile, strain, sigma, bends, features, diameter, window,
                           tuple(config.strain_thresholds), notes)  # fmt: skip


def no_products(config: NavConfig, why: str) -> IntegrityReport:
    """The report of a centreline no products can be made of (its CSVs: headers only), with
    ``why`` in its notes."""
    empty = np.zeros(0)
    fields_ = CurvatureProfile.__dataclass_fields__
    window = config.window()
    profile = CurvatureProfile(**{k: window if k == "window" else empty for k in fields_})
    return IntegrityReport(profile, empty, empty, [], [], config.outer_diameter(), window,
                           tuple(config.strain_thresholds), [why])  # fmt: skip


def _merged(reports: list[IntegrityReport]) -> IntegrityReport:
    """One report from those of consecutive pieces: rows one after the other, renumbered."""
    first = reports[0]
    fields_ = CurvatureProfile.__dataclass_fields__
    profile = CurvatureProfile(**{
        k: first.window if k == "window" else np.concatenate([getattr(r.profile, k)
                                                              for r in reports])
        for k in fields_
    })  # fmt: skip
    bends = [b for r in reports for b in r.bends]
    bends = [replace(b, number=i + 1) for i, b in enumerate(bends)]
    features = []
    for r, offset in zip(reports, np.cumsum([0] + [len(r.bends) for r in reports[:-1]]),
                         strict=True):  # fmt: skip
        for f in r.features:
            features.append(replace(f, bend=f.bend + int(offset) if f.bend else 0))
    features = [replace(f, number=i + 1) for i, f in enumerate(features)]
    notes = list(dict.fromkeys(n for r in reports for n in r.notes))
    strain = np.concatenate([r.strain_pct for r in reports])
    sigma = np.concatenate([r.sigma_strain_pct for r in reports])
    return IntegrityReport(profile, strain, sigma, bends, features, first.outer_diameter,
                           first.window, first.thresholds_pct, notes)  # fmt: skip
