"""GeoJSON (RFC 7946) and KML 2.2 export of a centreline and its markers.

Coordinates are WGS84 longitude and latitude in degrees (9 decimals, 0.1 mm) and the height
above the WGS84 ellipsoid in metres (4 decimals). GeoJSON defines its third coordinate as
exactly that. KML's ``absolute`` altitude mode is nominally relative to mean sea level, so
viewers such as Google Earth draw our ellipsoidal heights offset by the geoid undulation (tens
of metres); the KML document says so in its description. Files are written atomically.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from xml.sax.saxutils import escape

import numpy as np

from ..types import Marker, Trajectory
from .atomic import atomic_write
from .centreline import require_finite


def _coords(traj: Trajectory) -> list[list[float]]:
    lon = np.degrees(np.asarray(traj.lon, dtype=np.float64)).tolist()
    lat = np.degrees(np.asarray(traj.lat, dtype=np.float64)).tolist()
    h = np.asarray(traj.h, dtype=np.float64).tolist()
    return [
        [round(x, 9), round(y, 9), round(z, 4)]
        for x, y, z in zip(lon, lat, h, strict=True)
        if math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
    ]


def to_geojson(
    traj: Trajectory, markers: Sequence[Marker] = (), name: str = "centreline"
) -> dict[str, object]:
    """GeoJSON FeatureCollection: a LineString of the centreline ([lon, lat, h] degrees and
    ellipsoidal metres) with properties name, start/end time (s) and length (chainage, m), and
    one Point per marker with properties name, time_s, sigma_east/north/up_m."""
    coords = _coords(traj)
    d = np.asarray(traj.distance, dtype=np.float64)
    t = np.asarray(traj.t, dtype=np.float64)
    line_props: dict[str, object] = {
        "name": name,
        "kind": "centreline",
        "height_reference": "WGS84 ellipsoid",
        "samples": len(coords),
    }
    if len(t):
        line_props.update(
            start_time_s=float(t[0]),
            end_time_s=float(t[-1]),
            chainage_start_m=round(float(np.nanmin(d)), 4) if len(d) else None,
            chainage_end_m=round(float(np.nanmax(d)), 4) if len(d) else None,
        )
    features: list[dict[str, object]] = [
        {
            "type": "Feature",
            "geometry": {"type": "LineString", "coordinates": coords},
            "properties": line_props,
        }
    ]
    for m in markers:
        features.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "Point",
                    "coordinates": [
                        round(math.degrees(m.lon), 9),
                        round(math.degrees(m.lat), 9),
                        round(m.alt, 4),
                    ],
                },
                "properties": {
                    "name": m.name,
                    "kind": "marker",
                    "time_s": m.t,
                    "sigma_east_m": m.sigma_enu[0],
                    "sigma_north_m": m.sigma_enu[1],
                    "sigma_up_m": m.sigma_enu[2],
                },
            }
        )
    return {"type": "FeatureCollection", "features": features}


def write_geojson(
    path: str | os.PathLike[str], traj: Trajectory, markers: Sequence[Marker] = ()
) -> None:
    """Write :func:`to_geojson` to ``path`` (RFC 7946 GeoJSON, UTF-8); refuses non-finite
    samples."""
    require_finite(traj, f"{os.fspath(path)}: the centreline")
    doc = to_geojson(traj, markers, name=os.path.splitext(os.path.basename(path))[0])
    with atomic_write(path, "w") as f:
        json.dump(doc, f, separators=(",", ":"), allow_nan=False)
        f.write("\n")


def to_kml(traj: Trajectory, markers: Sequence[Marker] = (), name: str = "centreline") -> str:
    """KML 2.2 document: a LineString Placemark of the centreline and a Point Placemark per
    marker, altitudeMode absolute with WGS84 ellipsoidal heights (see the module docstring)."""
    line = " ".join(f"{x:.9f},{y:.9f},{z:.4f}" for x, y, z in _coords(traj))
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<kml xmlns="http://www.opengis.net/kml/2.2">',
        "<Document>",
        f"<name>{escape(name)}</name>",
        "<description>Pipe centreline from PipeNav. Altitudes are heights above the WGS84 "
        "ellipsoid in metres (not above mean sea level).</description>",
        '<Style id="centreline"><LineStyle><color>ff0000ff</color><width>3</width>'
        "</LineStyle></Style>",
        "<Placemark>",
        f"<name>{escape(name)}</name>",
        "<styleUrl>#centreline</styleUrl>",
        "<LineString>",
        "<tessellate>0</tessellate>",
        "<altitudeMode>absolute</altitudeMode>",
        f"<coordinates>{line}</coordinates>",
        "</LineString>",
        "</Placemark>",
    ]
    for m in markers:
        parts += [
            "<Placemark>",
            f"<name>{escape(m.name)}</name>",
            f"<description>marker passage at t = {m.t:.3f} s; survey sigma E/N/U "
            f"{m.sigma_enu[0]:.3f}/{m.sigma_enu[1]:.3f}/{m.sigma_enu[2]:.3f} m</description>",
            "<Point>",
            "<altitudeMode>absolute</altitudeMode>",
            f"<coordinates>{math.degrees(m.lon):.9f},{math.degrees(m.lat):.9f},"
            f"{m.alt:.4f}</coordinates>",
            "</Point>",
            "</Placemark>",
        ]
    parts += ["</Document>", "</kml>", ""]
    return "\n".join(parts)


def write_kml(
    path: str | os.PathLike[str], traj: Trajectory, markers: Sequence[Marker] = ()
) -> None:
    """Write :func:`to_kml` to ``path`` (UTF-8); refuses non-finite samples."""
    require_finite(traj, f"{os.fspath(path)}: the centreline")
    doc = to_kml(traj, markers, name=os.path.splitext(os.path.basename(path))[0])
    with atomic_write(path, "w") as f:
        f.write(doc)
