"""GeoJSON (RFC 7946) and KML 2.2 export of a centreline, its markers, and its bends and strain
features (points at the bend apexes and at the strain features' peaks).

Coordinates are WGS84 longitude and latitude in degrees (9 decimals, 0.1 mm) and the height
above the WGS84 ellipsoid in metres (4 decimals). GeoJSON defines its third coordinate as
exactly that. KML's ``absolute`` altitude mode is nominally relative to mean sea level, so
viewers such as Google Earth draw our ellipsoidal heights offset by the geoid undulation (tens
of metres); the KML document says so in its description. Files are written atomically.

About 410 lines, one module on purpose: GeoJSON and KML write the same features (centreline,
markers, bends, strain features, welds, bridges) from one set of helpers.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.geo.attitude import turn_deg
from pipe_nav_core.io.atomic import atomic_write, target_stem
from pipe_nav_core.io.centreline import require_finite
from pipe_nav_core.types import Marker, Trajectory

if TYPE_CHECKING:
    from pipe_nav_core.products.bends import PipeBend
    from pipe_nav_core.products.strain import StrainFeature
    from pipe_nav_core.products.welds import Weld


def _escape(text: str) -> str:
    """``text`` as XML character data: &, < and > as entities (what xml.sax.saxutils.escape
    does, without its import of urllib and email: 16-34 ms of every command's start)."""
    return text.replace("&", "&amp;").replace(">", "&gt;").replace("<", "&lt;")


def centreline_coords(traj: Trajectory) -> list[list[float]]:
    """The centreline's [lon, lat, h] (degrees to 9 decimals, m to 4) of every finite sample,
    as both formats write them: made once, and before the welds are known, by
    ``pipe-nav smooth`` (``coords`` of the writers)."""
    lon = np.degrees(np.asarray(traj.lon, dtype=np.float64)).tolist()
    lat = np.degrees(np.asarray(traj.lat, dtype=np.float64)).tolist()
    h = np.asarray(traj.h, dtype=np.float64).tolist()
    return [
        [round(x, 9), round(y, 9), round(z, 4)]
        for x, y, z in zip(lon, lat, h, strict=True)
        if math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
    ]


def _num(x: float, digits: int) -> float | None:
    """A rounded float for the properties; None (JSON null) when not finite."""
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None


def _point_coords(lat: float, lon: float, alt: float) -> list[float]:
    return [round(math.degrees(lon), 9), round(math.degrees(lat), 9), round(float(alt), 4)]


def bend_properties(b: PipeBend) -> dict[str, object]:
    """GeoJSON properties of a bend apex point (degrees, metres, outer diameters)."""
    return {
        "name": f"bend {b.number}",
        "kind": "bend",
        "number": int(b.number),
        "class": b.kind,
        "direction": b.direction,
        "angle_deg": _num(math.degrees(b.angle), 4),
        "sigma_angle_deg": _num(math.degrees(b.sigma_angle), 4),
        "radius_m": _num(b.radius, 3),
        "sigma_radius_m": _num(b.sigma_radius, 3),
        "radius_d": _num(b.radius_d, 2),
        "plane_deg": _num(float(turn_deg(b.plane, 2)), 2),
        "start_m": _num(b.start_m, 3),
        "apex_m": _num(b.apex_m, 3),
        "end_m": _num(b.end_m, 3),
        "time_s": _num(b.apex_t, 6),
    }


def strain_feature_properties(f: StrainFeature) -> dict[str, object]:
    """GeoJSON properties of a strain feature's peak point (percent, metres)."""
    return {
        "name": f"strain feature {f.number}",
        "kind": "strain_feature",
        "number": int(f.number),
        "threshold_pct": _num(f.threshold_pct, 6),
        "peak_pct": _num(f.peak_pct, 6),
        "sigma_peak_pct": _num(f.sigma_peak_pct, 6),
        "plane_deg": _num(float(turn_deg(f.plane, 2)), 2),
        "start_m": _num(f.start_m, 3),
        "peak_m": _num(f.peak_m, 3),
        "end_m": _num(f.end_m, 3),
        "length_m": _num(f.length_m, 3),
        "bend": int(f.bend),
        "construction": f.construction,
    }


def _point_feature(coords: list[float], props: dict[str, object]) -> dict[str, object]:
    return {
        "type": "Feature",
        "geometry": {"type": "Point", "coordinates": coords},
        "properties": props,
    }


def to_geojson(
    traj: Trajectory,
    markers: Sequence[Marker] = (),
    name: str = "centreline",
    *,
    bends: Sequence[PipeBend] = (),
    strain_features: Sequence[StrainFeature] = (),
    welds: Sequence[Weld] = (),
    bridges: Sequence[Mapping[str, float]] = (),
    coords: list[list[float]] | None = None,
) -> dict[str, object]:
    """GeoJSON FeatureCollection: a LineString of the centreline ([lon, lat, h] degrees and
    ellipsoidal metres; ``coords``: its :func:`centreline_coords`, when made already) with
    properties name, start/end time (s) and length (chainage, m), one Point per marker with
    properties name, time_s, sigma_east/north/up_m, one Point per bend at its apex (kind
    ``bend``, :func:`bend_properties`) and one per strain feature at its peak (kind
    ``strain_feature``, :func:`strain_feature_properties`) and one per girth weld (kind
    ``weld``, :func:`weld_properties`). Non-finite property values are null."""
    coords = centreline_coords(traj) if coords is None else coords
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
    for b in bends:
        features.append(_point_feature(_point_coords(b.lat, b.lon, b.alt), bend_properties(b)))
    for f in strain_features:
        features.append(
            _point_feature(_point_coords(f.lat, f.lon, f.alt), strain_feature_properties(f))
        )
    features += weld_features(welds)
    features += [bridge_feature(b) for b in bridges]
    return {"type": "FeatureCollection", "features": features}


def bridge_feature(b: Mapping[str, float]) -> dict[str, object]:
    """A LineString (kind ``unmapped``) across a stretch of pipe between two mapped segments
    (segments.Bridge as a dict): the straight line between its ends, with the odometer's
    bound on how far the pipe can be from it."""
    return {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": [
            _point_coords(b["lat0"], b["lon0"], b["alt0"]),
            _point_coords(b["lat1"], b["lon1"], b["alt1"])]},
        "properties": {"name": "unmapped", "kind": "unmapped", "start_time_s": b["t0"],
                       "end_time_s": b["t1"], "length_m": _num(b["length"], 3),
                       "chord_m": _num(b["chord"], 3), "within_m": _num(b["within"], 3)},
    }  # fmt: skip


def json_text(doc: object) -> str:
    """``doc`` as compact JSON and a newline. json.dumps, not json.dump: dump streams through
    the pure-Python encoder, many times slower on a centreline's coordinates (the same text)."""
    return json.dumps(doc, separators=(",", ":"), allow_nan=False) + "\n"


def write_geojson(
    path: str | os.PathLike[str],
    traj: Trajectory,
    markers: Sequence[Marker] = (),
    *,
    bends: Sequence[PipeBend] = (),
    strain_features: Sequence[StrainFeature] = (),
    welds: Sequence[Weld] = (),
    bridges: Sequence[Mapping[str, float]] = (),
    coords: list[list[float]] | None = None,
) -> None:
    """Write :func:`to_geojson` to ``path`` (RFC 7946 GeoJSON, UTF-8); refuses non-finite
    samples."""
    require_finite(traj, f"{os.fspath(path)}: the centreline")
    doc = to_geojson(traj, markers, name=target_stem(path),
                     bends=bends, strain_features=strain_features, welds=welds,
                     bridges=bridges, coords=coords)  # fmt: skip
    with atomic_write(path, "w") as f:
        f.write(json_text(doc))


def weld_properties(w: Weld) -> dict[str, object]:
    """GeoJSON properties of a girth weld point (metres, 0..1)."""
    return {
        "name": f"weld {w.number}",
        "kind": "weld",
        "number": int(w.number),
        "distance_m": _num(w.distance, 4),
        "joint_length_m": _num(w.joint_length, 4),
        "confidence": _num(w.confidence, 3),
        "sigma_h_m": _num(w.sigma_h, 4),
        "sigma_v_m": _num(w.sigma_v, 4),
        "time_s": _num(w.t, 6),
    }


def weld_features(welds: Sequence[Weld]) -> list[dict[str, object]]:
    """GeoJSON Point features of girth welds (:func:`weld_properties`)."""
    return [_point_feature(_point_coords(w.lat, w.lon, w.alt), weld_properties(w)) for w in welds]


def write_points_geojson(
    path: str | os.PathLike[str],
    points: Sequence[tuple[float, float, float, dict[str, object]]],
    name: str | None = None,
) -> None:
    """A GeoJSON FeatureCollection of Points: (lat rad, lon rad, ellipsoidal alt m,
    properties) each (``pipe-nav locate``'s features); non-finite property values become
    null. Atomic."""
    feats = [
        _point_feature(
            _point_coords(lat, lon, alt),
            {
                k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in props.items()
            },
        )  # fmt: skip
        for lat, lon, alt, props in points
    ]
    doc = {"type": "FeatureCollection",
           "name": name or target_stem(path),
           "features": feats}  # fmt: skip
    with atomic_write(path, "w") as f:
        f.write(json_text(doc))


def _kml_value(v: object) -> str:
    if v is None:
        return "unknown"
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def _kml_point(
    name: str, style: str, description: str, props: dict[str, object], lat: float,
    lon: float, alt: float,
) -> list[str]:  # fmt: skip
    """A Point Placemark with the GeoJSON properties as ExtendedData."""
    data = [
        f'<Data name="{_escape(k)}"><value>{_escape(_kml_value(v))}</value></Data>'
        for k, v in props.items()
        if k not in ("name", "kind")
    ]
    return [
        "<Placemark>",
        f"<name>{_escape(name)}</name>",
        f"<description>{_escape(description)}</description>",
        f"<styleUrl>#{style}</styleUrl>",
        "<ExtendedData>",
        *data,
        "</ExtendedData>",
        "<Point>",
        "<altitudeMode>absolute</altitudeMode>",
        f"<coordinates>{math.degrees(lon):.9f},{math.degrees(lat):.9f},{alt:.4f}</coordinates>",
        "</Point>",
        "</Placemark>",
    ]


def _kml_bend(b: PipeBend) -> list[str]:
    p = bend_properties(b)
    text = (f"{p['class']} bend, {p['direction']}: {math.degrees(b.angle):.2f} +- "
            f"{math.degrees(b.sigma_angle):.2f} deg, radius {b.radius:.1f} m "
            f"({b.radius_d:.1f} D), apex at chainage {b.apex_m:.2f} m "
            f"({b.start_m:.2f} - {b.end_m:.2f} m)")  # fmt: skip
    return _kml_point(str(p["name"]), "bend", text, p, b.lat, b.lon, b.alt)


def _kml_strain(f: StrainFeature) -> list[str]:
    p = strain_feature_properties(f)
    why = "no listed bend" if not f.bend else f"bend {f.bend}"
    if f.construction is not None:
        why += ", construction-related" if f.construction else ", not construction-related"
    text = (f"strain over {f.threshold_pct:g} %: peak {f.peak_pct:.4f} +- "
            f"{f.sigma_peak_pct:.4f} % at chainage {f.peak_m:.2f} m "
            f"({f.start_m:.2f} - {f.end_m:.2f} m, {f.length_m:.2f} m); {why}")  # fmt: skip
    return _kml_point(str(p["name"]), "strain_feature", text, p, f.lat, f.lon, f.alt)


def _kml_weld(w: Weld) -> list[str]:
    p = weld_properties(w)
    joint = f", joint {w.joint_length:.2f} m" if math.isfinite(w.joint_length) else ""
    text = (f"girth weld {w.number} at chainage {w.distance:.2f} m{joint}, confidence "
            f"{w.confidence:.2f}, sigma h/v {w.sigma_h:.3f}/{w.sigma_v:.3f} m")  # fmt: skip
    return _kml_point(str(p["name"]), "weld", text, p, w.lat, w.lon, w.alt)


def to_kml(
    traj: Trajectory,
    markers: Sequence[Marker] = (),
    name: str = "centreline",
    *,
    bends: Sequence[PipeBend] = (),
    strain_features: Sequence[StrainFeature] = (),
    welds: Sequence[Weld] = (),
    bridges: Sequence[Mapping[str, float]] = (),
    coords: list[list[float]] | None = None,
) -> str:
    """KML 2.2 document: a LineString Placemark of the centreline (``coords``: its
    :func:`centreline_coords`, when made already), a Point Placemark per marker, and one per
    bend apex, strain feature peak and girth weld (their GeoJSON properties as ExtendedData),
    altitudeMode absolute with WGS84 ellipsoidal heights (see the module docstring)."""
    coords = centreline_coords(traj) if coords is None else coords
    line = " ".join(f"{x:.9f},{y:.9f},{z:.4f}" for x, y, z in coords)
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<kml xmlns="http://www.opengis.net/kml/2.2">',
        "<Document>",
        f"<name>{_escape(name)}</name>",
        "<description>Pipe centreline from PipeNav. Altitudes are heights above the WGS84 "
        "ellipsoid in metres (not above mean sea level).</description>",
        '<Style id="centreline"><LineStyle><color>ff0000ff</color><width>3</width>'
        "</LineStyle></Style>",
    ]
    if bends:
        parts.append('<Style id="bend"><IconStyle><color>ff00a5ff</color></IconStyle></Style>')
    if strain_features:
        parts.append(
            '<Style id="strain_feature"><IconStyle><color>ffff00ff</color></IconStyle></Style>'
        )
    if welds:
        parts.append('<Style id="weld"><IconStyle><color>ff808080</color></IconStyle></Style>')
    parts += [
        "<Placemark>",
        f"<name>{_escape(name)}</name>",
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
            f"<name>{_escape(m.name)}</name>",
            f"<description>marker passage at t = {m.t:.3f} s; survey sigma E/N/U "
            f"{m.sigma_enu[0]:.3f}/{m.sigma_enu[1]:.3f}/{m.sigma_enu[2]:.3f} m</description>",
            "<Point>",
            "<altitudeMode>absolute</altitudeMode>",
            f"<coordinates>{math.degrees(m.lon):.9f},{math.degrees(m.lat):.9f},"
            f"{m.alt:.4f}</coordinates>",
            "</Point>",
            "</Placemark>",
        ]
    for b in bends:
        parts += _kml_bend(b)
    for f in strain_features:
        parts += _kml_strain(f)
    for w in welds:
        parts += _kml_weld(w)
    for x in bridges:
        ends = " ".join(f"{math.degrees(x[f'lon{i}']):.9f},{math.degrees(x[f'lat{i}']):.9f},"
                        f"{x[f'alt{i}']:.4f}" for i in (0, 1))  # fmt: skip
        parts += [
            "<Placemark>",
            "<name>unmapped</name>",
            f"<description>not mapped: {x['length']:.2f} m of pipe by the odometer, within "
            f"{x['within']:.2f} m of this line</description>",
            "<LineString><altitudeMode>absolute</altitudeMode>",
            f"<coordinates>{ends}</coordinates>",
            "</LineString>",
            "</Placemark>",
        ]
    parts += ["</Document>", "</kml>", ""]
    return "\n".join(parts)


def write_kml(
    path: str | os.PathLike[str],
    traj: Trajectory,
    markers: Sequence[Marker] = (),
    *,
    bends: Sequence[PipeBend] = (),
    strain_features: Sequence[StrainFeature] = (),
    welds: Sequence[Weld] = (),
    bridges: Sequence[Mapping[str, float]] = (),
    coords: list[list[float]] | None = None,
) -> None:
    """Write :func:`to_kml` to ``path`` (UTF-8); refuses non-finite samples."""
    require_finite(traj, f"{os.fspath(path)}: the centreline")
    doc = to_kml(traj, markers, name=target_stem(path),
                 bends=bends, strain_features=strain_features, welds=welds,
                 bridges=bridges, coords=coords)  # fmt: skip
    with atomic_write(path, "w") as f:
        f.write(doc)
