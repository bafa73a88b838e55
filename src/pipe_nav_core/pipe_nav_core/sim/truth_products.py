"""The exact integrity products of a simulated pipe: curvature, bending strain and the bend list,
in closed form from the geometry's features (never by differentiating positions).

Conventions are those of :mod:`pipe_nav_core.products` (INTERFACES.md, "Integrity products"):

- pointwise curvature at chainage s: vertical = d(pitch)/ds (positive bending upward),
  horizontal = cos(pitch) d(azimuth)/ds (positive turning right), total = their magnitude (the
  axis direction (cos p sin a, cos p cos a, sin p) has dT/ds = p' u + cos(p) a' r with u, r
  orthonormal, up and right), plane = atan2(horizontal, vertical) in [0, 2 pi);
- window-mean curvature over w m centred on s (what the estimator reports,
  :func:`pipe_nav_core.products.curvature.windowed_curvature`): the angle between the exact axis
  at s - w/2 and s + w/2 divided by w, split into components along the up and right directions
  of the mid-chord axis, the window shrinking at the pipe's ends;
- bending strain = total curvature x outer diameter / 2, in percent.

The bend list (:func:`truth_bends`): every :class:`~pipe_nav_core.sim.geometry.Bend` is one
bend from the start of its entry transition to the end of its exit transition, apex in the
middle of its arc; a :class:`~pipe_nav_core.sim.geometry.Sag` is three bends, the lobes of its
curvature, which is shaped as cos(X) - cos(2X) (X = 2 pi x) with zero crossings at x = 1/3 and
2/3: the outer lobes turn by 3 sqrt(3) / 8 A each and the middle one by 3 sqrt(3) / 4 A
(A the sag's amplitude), with peak curvatures 9/8 and 2 times A pi / L (at cos X = 1/4 and
X = pi). Features of the two planes that overlap are one 3-D bend, as the estimator sees them.
Angle (3-D, between the axes at the bend's ends), radius (1 / the peak total curvature), apex
(middle of the stretch over half the peak curvature, the middle of the arc for a single bend),
plane and direction (:func:`pipe_nav_core.products.bends.bend_direction`) are evaluated from
the closed-form direction and curvature; only the integral of the horizontal component of a 3-D
bend uses quadrature.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.products.bends import PipeBend, bend_class, bend_direction
from pipe_nav_core.products.curvature import CurvatureProfile

if TYPE_CHECKING:
    from pipe_nav_core.config import NavConfig
    from pipe_nav_core.sim.geometry import PipeGeometry
    from pipe_nav_core.sim.run import SimRun

FloatArray = NDArray[np.float64]

SAG_OUTER_ANGLE = 3.0 * math.sqrt(3.0) / 8.0  # x amplitude: turn of each outer lobe of a sag
SAG_MIDDLE_ANGLE = 3.0 * math.sqrt(3.0) / 4.0  # x amplitude: turn of the middle lobe
SAG_OUTER_PEAK = 9.0 / 8.0  # x amplitude * pi / length: peak curvature of an outer lobe
SAG_MIDDLE_PEAK = 2.0  # x amplitude * pi / length: peak curvature of the middle lobe
SAG_OUTER_PEAK_X = math.acos(0.25) / (2.0 * math.pi)  # where the first lobe peaks, x in [0, 1]


def point_curvature(geometry: PipeGeometry, s: ArrayLike) -> dict[str, FloatArray]:
    """Exact curvature at chainages ``s`` (m): vertical, horizontal, total (1/m) and plane (rad)."""
    _, pitch, k_az, k_pitch = geometry.direction(s)
    vertical = k_pitch
    horizontal = np.cos(pitch) * k_az
    return {
        "vertical": vertical,
        "horizontal": horizontal,
        "total": np.hypot(vertical, horizontal),
        "plane": np.mod(np.arctan2(horizontal, vertical), 2.0 * math.pi),
    }


def chord_curvature(t0: FloatArray, t1: FloatArray, width: FloatArray) -> dict[str, FloatArray]:
    """Mean curvature of a turn from unit axis t0 to t1 (..., 3) over ``width`` m, split as
    :func:`pipe_nav_core.products.curvature.windowed_curvature` does (same formulas)."""
    t0 = np.asarray(t0, dtype=np.float64).reshape(-1, 3)
    t1 = np.asarray(t1, dtype=np.float64).reshape(-1, 3)
    w = np.maximum(np.asarray(width, dtype=np.float64).reshape(-1), 1e-9)
    chord = t1 - t0
    norm = np.linalg.norm(chord, axis=1)
    turn = 2.0 * np.arcsin(np.clip(0.5 * norm, 0.0, 1.0))
    mid = t0 + t1
    mid /= np.maximum(np.linalg.norm(mid, axis=1, keepdims=True), 1e-12)
    pitch = np.arcsin(np.clip(mid[:, 2], -1.0, 1.0))
    az = np.arctan2(mid[:, 0], mid[:, 1])
    sp, cp, sa, ca = np.sin(pitch), np.cos(pitch), np.sin(az), np.cos(az)
    up = np.stack([-sp * sa, -sp * ca, cp], axis=1)
    right = np.stack([ca, -sa, np.zeros_like(ca)], axis=1)
    scale = np.where(norm > 1e-15, turn / np.maximum(norm, 1e-15), 1.0) / w
    vertical = np.einsum("ij,ij->i", chord, up) * scale
    horizontal = np.einsum("ij,ij->i", chord, right) * scale
    return {
        "vertical": vertical,
        "horizontal": horizontal,
        "total": turn / w,
        "plane": np.mod(np.arctan2(horizontal, vertical), 2.0 * math.pi),
        "turn": turn,
    }


def window_curvature(geometry: PipeGeometry, s: ArrayLike, window: float) -> dict[str, FloatArray]:
    """Exact mean curvature over ``window`` m of chainage centred on each of ``s`` (m), the
    window shrinking to the pipe at its ends: vertical, horizontal, total (1/m), plane (rad)."""
    if not (math.isfinite(window) and window > 0):
        raise ValueError(f"the curvature window must be a positive number of metres, not {window}")
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    lo = np.clip(s - 0.5 * window, 0.0, geometry.length)
    hi = np.clip(s + 0.5 * window, 0.0, geometry.length)
    out = chord_curvature(geometry.tangent_enu(lo), geometry.tangent_enu(hi), hi - lo)
    out.pop("turn")
    return out


def strain_pct(total_curvature: ArrayLike, outer_diameter: float) -> FloatArray:
    """Bending strain (percent) of a total curvature (1/m) for an outer diameter (m)."""
    return np.asarray(total_curvature, dtype=np.float64) * (0.5 * outer_diameter * 100.0)


@dataclass(frozen=True)
class TruthBend:
    """One exact bend. Chainages m (true centreline chainage); angle, plane, vertical and
    horizontal (the integrated turns of either component) rad; radius m (minimum); lat, lon
    rad, alt m at the apex; source: ``bend``, ``sag lobe`` or ``3-D`` (features merged)."""

    number: int
    start_m: float
    apex_m: float
    end_m: float
    angle: float
    radius: float
    plane: float
    direction: str
    vertical: float
    horizontal: float
    lat: float
    lon: float
    alt: float
    source: str

    @property
    def length_m(self) -> float:
        return self.end_m - self.start_m


@dataclass(frozen=True)
class _Piece:
    start: float
    end: float
    source: str
    apex: float | None  # exact apex of a single bend
    peaks: tuple[float, ...]  # chainages of its exact curvature peaks


def _pieces(geometry: PipeGeometry) -> list[_Piece]:
    """Each bend, and each lobe of each sag, as one piece with its exact peak chainages."""
    out: list[_Piece] = []
    for plane in ("h", "v"):
        for e in geometry._planes[plane]:  # noqa: SLF001 - the sim package's own closed forms
            if e.kind == "bend":
                mid = 0.5 * (e.start + e.end)
                # the constant-curvature arc (or its single point when the ramps meet)
                out.append(_Piece(e.start, e.end, "bend", mid, (mid, e.start + e.lr, e.s1)))
            else:
                ln = e.length
                third = 1.0 / 3.0
                for x0, xp in ((0.0, SAG_OUTER_PEAK_X), (third, 0.5),
                               (2.0 * third, 1.0 - SAG_OUTER_PEAK_X)):  # fmt: skip
                    a, b = e.start + x0 * ln, e.start + (x0 + third) * ln
                    out.append(_Piece(a, b, "sag lobe", None, (e.start + xp * ln,)))
    lo, hi = 0.0, geometry.length
    out = [
        _Piece(max(p.start, lo), min(p.end, hi), p.source, p.apex, p.peaks)
        for p in out
        if p.end > lo and p.start < hi
    ]
    return sorted(out, key=lambda p: p.start)


def _groups(pieces: list[_Piece]) -> list[list[_Piece]]:
    """Pieces that overlap (by more than a micrometre) joined into one group."""
    groups: list[list[_Piece]] = []
    end = -math.inf
    for p in pieces:
        if groups and p.start < end - 1e-6:
            groups[-1].append(p)
            end = max(end, p.end)
        else:
            groups.append([p])
            end = p.end
    return groups


def _measure(geometry: PipeGeometry, group: list[_Piece]) -> TruthBend:
    a = min(p.start for p in group)
    b = max(p.end for p in group)
    peaks = [x for p in group for x in p.peaks if a <= x <= b]
    s = np.unique(np.concatenate([np.linspace(a, b, max(801, int(math.ceil((b - a) / 0.005)) + 1)),
                                  peaks]))  # fmt: skip
    k = point_curvature(geometry, s)
    total = k["total"]
    peak = float(total.max())
    t0, t1 = geometry.tangent_enu(np.array([a, b]))
    angle = 2.0 * math.asin(min(1.0, 0.5 * float(np.linalg.norm(t1 - t0))))
    _, (p0, p1), _, _ = geometry.direction(np.array([a, b]))
    vertical = float(p1 - p0)
    horizontal = float(np.trapezoid(k["horizontal"], s))
    if len(group) == 1 and group[0].apex is not None:
        apex = float(group[0].apex)
    else:
        over = np.flatnonzero(total >= 0.5 * peak)
        i0, i1 = int(over[0]), int(over[-1])

        def cross(i: int, j: int) -> float:  # half-peak crossing between samples i and j
            if not 0 <= j < len(s):
                return float(s[i])
            f = (0.5 * peak - total[j]) / (total[i] - total[j])
            return float(s[j] + f * (s[i] - s[j]))

        apex = 0.5 * (cross(i0, i0 - 1) + cross(i1, i1 + 1))
    lat, lon, alt = (float(x) for x in geometry.position(apex))
    source = group[0].source if len(group) == 1 else "3-D"
    return TruthBend(
        number=0,
        start_m=float(a),
        apex_m=apex,
        end_m=float(b),
        angle=angle,
        radius=1.0 / peak if peak > 0 else math.inf,
        plane=math.atan2(horizontal, vertical) % (2.0 * math.pi),
        direction=bend_direction(vertical, horizontal),
        vertical=vertical,
        horizontal=horizontal,
        lat=lat,
        lon=lon,
        alt=alt,
        source=source,
    )


def truth_bends(
    geometry: PipeGeometry, min_angle: float = math.radians(1.0), max_radius: float = math.inf
) -> list[TruthBend]:
    """The exact bend list (see the module) of bends turning by at least ``min_angle`` rad with a
    minimum radius under ``max_radius`` m, numbered 1, 2, ... in chainage order."""
    found = [_measure(geometry, g) for g in _groups(_pieces(geometry))]
    keep = [b for b in found if b.angle >= min_angle and b.radius < max_radius]
    return [
        TruthBend(i + 1, *[getattr(b, f) for f in TruthBend.__dataclass_fields__][1:])
        for i, b in enumerate(keep)
    ]


# --------------------------------------------------------------------------------------------
# The truth products of a simulated run, in the layouts of the estimated ones
# --------------------------------------------------------------------------------------------


def run_config(run: SimRun) -> NavConfig:
    """The estimator settings of a run's scenario (products settings: outer diameter, window,
    bend thresholds) as a NavConfig."""
    from pipe_nav_core.config import NavConfig

    return NavConfig.from_dict(run.scenario.estimator_settings())


def _geometry(run: SimRun) -> PipeGeometry:
    return run.geometry if run.geometry is not None else run.scenario.build_geometry()


def truth_profile(
    run: SimRun,
    config: NavConfig | None = None,
    *,
    spacing: float = 0.5,
    window: float | None = None,
) -> CurvatureProfile:
    """The exact window-mean curvature profile of a run every ``spacing`` m of true chainage,
    at the window of ``config`` (default: the scenario's settings) or ``window`` m; sigma 0,
    t the time the pig first reaches each chainage."""
    geometry = _geometry(run)
    cfg = config or run_config(run)
    w = float(window) if window is not None else cfg.window()
    s = np.arange(0.0, geometry.length + 1e-9, spacing)
    k = window_curvature(geometry, s, w)
    az, pitch, _, _ = geometry.direction(s)
    lat, lon, alt = geometry.position(s)
    t = run.motion.time_at_chainage(s) if run.motion is not None else np.interp(
        s, run.truth.distance, run.truth.t)  # fmt: skip
    return CurvatureProfile(distance=s, t=np.asarray(t, dtype=np.float64), lat=lat, lon=lon,
                            alt=alt, vertical=k["vertical"], horizontal=k["horizontal"],
                            total=k["total"], plane=k["plane"], sigma=np.zeros_like(s), window=w,
                            pitch=pitch, azimuth=az)  # fmt: skip


def as_pipe_bends(run: SimRun, bends: list[TruthBend], config: NavConfig) -> list[PipeBend]:
    """Truth bends as :class:`~pipe_nav_core.products.bends.PipeBend` (sigmas 0, apex time the
    pig's passage, class by the settings' limits), for the bend CSV writer."""
    from pipe_nav_core.geo.attitude import quat_from_euler

    geometry = _geometry(run)
    d = config.outer_diameter()
    out = []
    for b in bends:
        az, pitch, _, _ = geometry.direction(np.array([b.apex_m]))
        t = (float(run.motion.time_at_chainage(b.apex_m)) if run.motion is not None
             else float(np.interp(b.apex_m, run.truth.distance, run.truth.t)))  # fmt: skip
        quat = quat_from_euler(0.0, float(pitch[0]), float(az[0])).reshape(4)
        out.append(PipeBend(
            number=b.number, start_m=b.start_m, apex_m=b.apex_m, end_m=b.end_m, lat=b.lat,
            lon=b.lon, alt=b.alt, angle=b.angle, sigma_angle=0.0, radius=b.radius,
            sigma_radius=0.0, radius_d=b.radius / d, plane=b.plane, direction=b.direction,
            kind=bend_class(b.radius / d, config.bend_class_limits), apex_t=t,
            apex_quat_nb=tuple(float(x) for x in quat),  # type: ignore[arg-type]
        ))  # fmt: skip
    return out


def truth_product_paths(out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``<stem>_truth_strain.csv`` and ``<stem>_truth_bends.csv`` beside the bag ``out``."""
    p = Path(out)
    return p.with_name(p.stem + "_truth_strain.csv"), p.with_name(p.stem + "_truth_bends.csv")


def write_truth_products(
    out: str | os.PathLike[str], run: SimRun, config: NavConfig | None = None
) -> tuple[Path, Path]:
    """Write the exact strain profile (window-mean at the settings' window, every 0.5 m of true
    chainage) and the exact bend list (at the settings' minimum angle and threshold radius)
    beside the simulated bag ``out``, in the layouts of ``RUN_strain.csv`` and
    ``RUN_bends.csv`` (INTERFACES.md; sigmas 0). Returns the two paths."""
    from pipe_nav_core.io.products_csv import write_bends_csv, write_strain_csv

    cfg = config or run_config(run)
    strain_path, bends_path = truth_product_paths(out)
    profile = truth_profile(run, cfg)
    strain = strain_pct(profile.total, cfg.outer_diameter())
    write_strain_csv(strain_path, profile, strain, np.zeros_like(strain))
    bends = truth_bends(_geometry(run), cfg.bend_min_angle, cfg.bend_threshold_radius)
    write_bends_csv(bends_path, as_pipe_bends(run, bends, cfg))
    return strain_path, bends_path


__all__ = [
    "TruthBend",
    "as_pipe_bends",
    "chord_curvature",
    "point_curvature",
    "run_config",
    "strain_pct",
    "truth_bends",
    "truth_product_paths",
    "truth_profile",
    "window_curvature",
    "write_truth_products",
]
