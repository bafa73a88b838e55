"""The files of ``pipe-nav compare``: MOVEMENT.csv (INTERFACES.md), its GeoJSON and its PNG.

MOVEMENT.csv: exactly the documented columns
``weld,distance_m,latitude_deg,longitude_deg,altitude_m,d_east_m,d_north_m,d_up_m,
sigma_d_east_m,sigma_d_north_m,sigma_d_up_m,significant``, then ``anchor`` (weld or bend),
``weld_b``, ``distance_b_m`` (the point in run B), ``d_m`` (3-D length), ``mahalanobis``,
``d_curvature_vertical_per_m``, ``d_curvature_horizontal_per_m``, ``d_strain_pct``. GeoJSON: one
Point per compared point (run A's position, the CSV's values as properties) and one LineString
per movement interval. PNG: the displacement components along the chainage with their 3-sigma
bands, the 3-D length against the threshold, and the movement intervals shaded. All written
atomically; non-finite values are refused.
"""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.io.atomic import atomic_write, target_stem
from pipe_nav_core.io.gis import json_text

if TYPE_CHECKING:
    from pipe_nav_core.products.movement import MovementReport, PointMovement

MOVEMENT_COLUMNS = [
    "weld",
    "distance_m",
    "latitude_deg",
    "longitude_deg",
    "altitude_m",
    "d_east_m",
    "d_north_m",
    "d_up_m",
    "sigma_d_east_m",
    "sigma_d_north_m",
    "sigma_d_up_m",
    "significant",
    "anchor",
    "weld_b",
    "distance_b_m",
    "d_m",
    "mahalanobis",
    "d_curvature_vertical_per_m",
    "d_curvature_horizontal_per_m",
    "d_strain_pct",
]
_FMT = ",".join(["{}", "{:.3f}", "{:.9f}", "{:.9f}", "{:.4f}", "{:.4f}", "{:.4f}", "{:.4f}",
                 "{:.4f}", "{:.4f}", "{:.4f}", "{}", "{}", "{}", "{:.3f}", "{:.4f}", "{:.2f}",
                 "{:.4e}", "{:.4e}", "{:.6f}"])  # fmt: skip


def movement_row(p: PointMovement) -> list[object]:
    """A compared point as the values of MOVEMENT_COLUMNS (degrees for people)."""
    return [p.weld, p.distance, math.degrees(p.lat), math.degrees(p.lon), p.alt, *p.d_enu,
            *p.sigma_enu, int(p.significant), p.anchor, p.weld_b, p.distance_b, p.magnitude,
            p.mahalanobis, p.d_curvature_vertical, p.d_curvature_horizontal,
            p.d_strain_pct]  # fmt: skip


def write_movement_csv(path: str | os.PathLike[str], report: MovementReport) -> None:
    """MOVEMENT.csv, one row per compared point in run A's chainage order."""
    rows = [movement_row(p) for p in report.points]
    for r in rows:
        if not all(math.isfinite(float(v)) for v in r if not isinstance(v, str)):
            raise ValueError(f"{os.fspath(path)}: a movement row is not finite: refusing to write")
    with atomic_write(path, "w", newline="") as f:
        f.write(",".join(MOVEMENT_COLUMNS) + "\n")
        f.write("".join(_FMT.format(*r) + "\n" for r in rows))


def to_movement_geojson(report: MovementReport, name: str = "movement") -> dict[str, object]:
    """GeoJSON FeatureCollection of the compared points and the movement intervals."""
    features: list[dict[str, object]] = []
    for p, row in zip(report.points, (movement_row(p) for p in report.points), strict=True):
        props = {k: (round(v, 9) if isinstance(v, float) else v)
                 for k, v in zip(MOVEMENT_COLUMNS, row, strict=True)}  # fmt: skip
        props.update(name=f"{p.anchor} {p.weld}", kind="movement_point")
        features.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [
            round(math.degrees(p.lon), 9), round(math.degrees(p.lat), 9), round(p.alt, 4)]},
            "properties": props})  # fmt: skip
    for iv in report.intervals:
        inside = [p for p in report.points if iv.start_m <= p.distance <= iv.end_m]
        coords = [[round(math.degrees(p.lon), 9), round(math.degrees(p.lat), 9),
                   round(p.alt, 4)] for p in inside]  # fmt: skip
        geom = ({"type": "LineString", "coordinates": coords} if len(coords) > 1
                else {"type": "Point", "coordinates": coords[0]})  # fmt: skip
        features.append({"type": "Feature", "geometry": geom, "properties": {
            "name": f"movement {iv.number}", "kind": "movement_interval",
            "start_m": round(iv.start_m, 3), "end_m": round(iv.end_m, 3),
            "peak_m": round(iv.peak_m, 3), "peak_d_m": round(iv.peak_magnitude, 4),
            "peak_d_east_m": round(float(iv.peak_d_enu[0]), 4),
            "peak_d_north_m": round(float(iv.peak_d_enu[1]), 4),
            "peak_d_up_m": round(float(iv.peak_d_enu[2]), 4), "points": iv.points}})  # fmt: skip
    return {"type": "FeatureCollection", "name": name, "features": features}


def write_movement_geojson(
    path: str | os.PathLike[str], report: MovementReport, name: str | None = None
) -> None:
    """Write :func:`to_movement_geojson` (RFC 7946, UTF-8); name: default the file's stem."""
    doc = to_movement_geojson(report, name or target_stem(path))
    with atomic_write(path, "w") as f:
        f.write(json_text(doc))


def plot_movement(path: str | os.PathLike[str], report: MovementReport, title: str = "") -> None:
    """The displacement profile PNG (module docstring), headless (Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pts = report.points
    s = np.array([p.distance for p in pts])
    d = np.array([p.d_enu for p in pts]).reshape(-1, 3)
    sig = np.array([p.sigma_enu for p in pts]).reshape(-1, 3)
    mag = np.linalg.norm(d, axis=1)
    fig = Figure(figsize=(12, 8), dpi=100)
    FigureCanvasAgg(fig)
    grid = dict(left=0.08, right=0.97, bottom=0.08, top=0.92)
    ax1, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw=grid)
    fig.suptitle(title or "Run-to-run movement (B - A)", fontsize=13)
    for k, (lab, col) in enumerate((("east", "tab:blue"), ("north", "tab:orange"),
                                    ("up", "tab:green"))):  # fmt: skip
        if len(s):
            ax1.fill_between(s, -report.n_sigma * sig[:, k], report.n_sigma * sig[:, k],
                             color=col, alpha=0.12, lw=0)  # fmt: skip
            ax1.plot(s, d[:, k], ".-", color=col, lw=1, ms=3, label=f"d_{lab}")
    ax1.set_ylabel("displacement [m]")
    ax1.set_title(f"components with their {report.n_sigma:g}-sigma bands")
    ax2.plot(s, mag, ".-", color="k", lw=1, ms=3, label="|d|")
    ax2.axhline(report.threshold, color="tab:red", ls="--", lw=1,
                label=f"threshold {report.threshold:g} m")  # fmt: skip
    sigs = [p for p in pts if p.significant]
    if sigs:
        ax2.plot([p.distance for p in sigs], [p.magnitude for p in sigs], "o", color="tab:red",
                 ms=5, label="significant")  # fmt: skip
    for ax in (ax1, ax2):
        for iv in report.intervals:
            ax.axvspan(iv.start_m - 2.0, iv.end_m + 2.0, color="tab:red", alpha=0.12, lw=0)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    ax2.set_xlabel("chainage of run A [m]")
    ax2.set_ylabel("|d| [m]")
    ax2.set_title(f"{len(report.intervals)} movement interval(s) (shaded)")
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png")


__all__ = [
    "MOVEMENT_COLUMNS",
    "movement_row",
    "plot_movement",
    "to_movement_geojson",
    "write_movement_csv",
    "write_movement_geojson",
]
