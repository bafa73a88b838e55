"""The integrity products' CSV files (INTERFACES.md): ``RUN_strain.csv``, ``RUN_bends.csv``,
and ``RUN_strain_features.csv``.

The first columns of the strain and bend files are exactly the documented ones; further
columns follow (``sigma_curvature_per_m``, ``time_s``, the strain and its sigma in
microstrain; ``sigma_radius_m``, ``apex_time_s``, ``radius_resolved``, the apex's sigmas).
Chainages m of distance_m; latitude/longitude WGS84 degrees with 9 decimals; altitude
ellipsoidal m; angles degrees; curvature 1/m; strain percent; sigmas one-sigma. Files are
written atomically and refuse non-finite values (a NaN never reaches an output).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.geo.attitude import turn_deg
from pipe_nav_core.io.atomic import atomic_write

if TYPE_CHECKING:  # (products imports io: gis, which writes the products, imports this)
    from pipe_nav_core.products import CurvatureProfile, PipeBend, StrainFeature

STRAIN_COLUMNS = [
    "distance_m",
    "latitude_deg",
    "longitude_deg",
    "altitude_m",
    "curvature_vertical_per_m",
    "curvature_horizontal_per_m",
    "curvature_total_per_m",
    "curvature_plane_deg",
    "strain_pct",
    "sigma_strain_pct",
    "sigma_curvature_per_m",
    "time_s",
    "strain_microstrain",
    "sigma_strain_microstrain",
]
BEND_COLUMNS = [
    "bend",
    "start_m",
    "apex_m",
    "end_m",
    "latitude_deg",
    "longitude_deg",
    "altitude_m",
    "angle_deg",
    "sigma_angle_deg",
    "radius_m",
    "radius_d",
    "plane_deg",
    "direction",
    "class",
    "sigma_radius_m",
    "apex_time_s",
    "radius_resolved",
    "sigma_h_m",
    "sigma_v_m",
]
FEATURE_COLUMNS = [
    "feature",
    "threshold_pct",
    "start_m",
    "peak_m",
    "end_m",
    "length_m",
    "latitude_deg",
    "longitude_deg",
    "altitude_m",
    "peak_strain_pct",
    "sigma_strain_pct",
    "plane_deg",
    "bend",
    "construction",
]


def _finite(values: Sequence[float], what: str) -> None:
    bad = [v for v in values if isinstance(v, float) and not math.isfinite(v)]
    if bad:
        raise ValueError(f"{what}: {len(bad)} value(s) are not finite: refusing to write them")


def write_strain_csv(
    path: str | os.PathLike[str],
    profile: CurvatureProfile,
    strain_pct: np.ndarray,
    sigma_strain_pct: np.ndarray,
) -> None:
    """The strain CSV: one row per profile row (chainage step)."""
    cols = [profile.distance, np.degrees(profile.lat), np.degrees(profile.lon), profile.alt,
            profile.vertical, profile.horizontal, profile.total, turn_deg(profile.plane, 2),
            strain_pct, sigma_strain_pct, profile.sigma, profile.t, 1e4 * strain_pct,
            1e4 * sigma_strain_pct]  # fmt: skip
    data = np.column_stack([np.asarray(c, dtype=np.float64) for c in cols]).reshape(-1, len(cols))
    if not np.isfinite(data).all():
        n = int((~np.isfinite(data).all(axis=1)).sum())
        raise ValueError(f"{os.fspath(path)}: {n} strain rows are not finite: refusing to write")
    fmt = ",".join(["{:.4f}", "{:.9f}", "{:.9f}", "{:.4f}", "{:.4e}", "{:.4e}", "{:.4e}",
                    "{:.2f}", "{:.6f}", "{:.6f}", "{:.3e}", "{:.6f}", "{:.2f}",
                    "{:.2f}"])  # fmt: skip
    with atomic_write(path, "w", newline="") as f:
        f.write(",".join(STRAIN_COLUMNS) + "\n")
        f.write("".join(fmt.format(*row) + "\n" for row in data.tolist()))


def bend_row(b: PipeBend) -> list[object]:
    """A bend as the values of BEND_COLUMNS (degrees for people)."""
    return [b.number, b.start_m, b.apex_m, b.end_m, math.degrees(b.lat), math.degrees(b.lon),
            b.alt, math.degrees(b.angle), math.degrees(b.sigma_angle), b.radius, b.radius_d,
            float(turn_deg(b.plane, 1)), b.direction, b.kind, b.sigma_radius, b.apex_t,
            int(b.radius_resolved), b.sigma_h, b.sigma_v]  # fmt: skip


def write_bends_csv(path: str | os.PathLike[str], bends: Sequence[PipeBend]) -> None:
    """The bend list CSV, one row per bend in chainage order."""
    fmt = ",".join(["{}", "{:.3f}", "{:.3f}", "{:.3f}", "{:.9f}", "{:.9f}", "{:.4f}", "{:.3f}",
                    "{:.3f}", "{:.4f}", "{:.2f}", "{:.1f}", "{}", "{}", "{:.4f}",
                    "{:.6f}", "{}", "{:.4f}", "{:.4f}"])  # fmt: skip
    rows = [bend_row(b) for b in bends]
    for r in rows:
        _finite(r[:-2], os.fspath(path))  # the apex sigmas may be unknown (empty)
    text = "".join(fmt.format(*r).replace("nan", "") + "\n" for r in rows)
    with atomic_write(path, "w", newline="") as f:
        f.write(",".join(BEND_COLUMNS) + "\n")
        f.write(text)


def feature_row(x: StrainFeature) -> list[object]:
    """A strain feature as the values of FEATURE_COLUMNS; construction 1/0, empty unknown."""
    construction = "" if x.construction is None else int(x.construction)
    return [x.number, x.threshold_pct, x.start_m, x.peak_m, x.end_m, x.length_m,
            math.degrees(x.lat), math.degrees(x.lon), x.alt, x.peak_pct, x.sigma_peak_pct,
            float(turn_deg(x.plane, 1)), x.bend, construction]  # fmt: skip


def write_strain_features_csv(
    path: str | os.PathLike[str], features: Sequence[StrainFeature]
) -> None:
    """The strain features CSV, one row per stretch over a threshold."""
    fmt = ",".join(["{}", "{:.3f}", "{:.3f}", "{:.3f}", "{:.3f}", "{:.3f}", "{:.9f}", "{:.9f}",
                    "{:.4f}", "{:.4f}", "{:.4f}", "{:.1f}", "{}", "{}"])  # fmt: skip
    rows = [feature_row(x) for x in features]
    for r in rows:
        _finite(r, os.fspath(path))
    with atomic_write(path, "w", newline="") as f:
        f.write(",".join(FEATURE_COLUMNS) + "\n")
        f.write("".join(fmt.format(*r) + "\n" for r in rows))
