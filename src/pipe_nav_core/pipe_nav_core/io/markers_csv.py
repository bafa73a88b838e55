"""Marker (AGM) CSV files and merging them with the markers recorded in a bag.

Format (INTERFACES.md): header ``name,time_s,latitude_deg,longitude_deg,altitude_m,sigma_h_m,
sigma_v_m``, one row per marker passage. time_s: passage time on the bag's header-stamp clock,
s; latitude/longitude WGS84 degrees; altitude ellipsoidal m; sigma_h_m / sigma_v_m: one-sigma
horizontal (each of east and north) and vertical survey uncertainty, m (empty: 0.05 m).
Columns may come in any order; extra columns are ignored; blank lines and lines starting
with '#' are skipped.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
from collections.abc import Iterable, Sequence

from pipe_nav_core.errors import MarkerCsvError
from pipe_nav_core.io.atomic import atomic_write
from pipe_nav_core.io.rosmsg import DEFAULT_MARKER_SIGMA_M
from pipe_nav_core.types import Marker, markers_sorted

MARKER_COLUMNS = [
    "name",
    "time_s",
    "latitude_deg",
    "longitude_deg",
    "altitude_m",
    "sigma_h_m",
    "sigma_v_m",
]
_REQUIRED = MARKER_COLUMNS[:5]




def _num(path: str, line: int, col: str, text: str, default: float | None = None) -> float:
    text = text.strip()
    if text == "" and default is not None:
        return default
    try:
        v = float(text)
    except ValueError:
        raise MarkerCsvError(f"{path}:{line}: {col} {text!r} is not a number") from None
    if not math.isfinite(v):
        raise MarkerCsvError(f"{path}:{line}: {col} {text!r} is not finite")
    return v


def read_markers_csv(path: str | os.PathLike[str]) -> list[Marker]:
    """Markers from a CSV file (see the module docstring), sorted by passage time. An empty
    time_s is a surveyed marker whose passage is not known yet (NaN; such markers keep the
    file's order, after the timed ones): they serve as a survey, not as position fixes.
    Latitude/longitude are converted to radians. Raises MarkerCsvError on bad content."""
    p = os.fspath(path)
    try:
        with open(p, newline="", encoding="utf-8-sig") as f:
            rows = [(i + 1, r) for i, r in enumerate(csv.reader(f))]
    except OSError as exc:
        raise MarkerCsvError(f"{p}: cannot read ({exc.strerror or exc})") from None
    rows = [
        (n, r)
        for n, r in rows
        if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")
    ]
    if not rows:
        raise MarkerCsvError(f"{p}: empty file (expected the header {','.join(MARKER_COLUMNS)})")
    _, header = rows[0]
    cols = {c.strip(): i for i, c in enumerate(header)}
    missing = [c for c in _REQUIRED if c not in cols]
    if missing:
        raise MarkerCsvError(
            f"{p}:1: missing column(s) {', '.join(missing)} "
            f"(expected header {','.join(MARKER_COLUMNS)})"
        )
    out: list[Marker] = []
    names: set[str] = set()
    for line, r in rows[1:]:

        def cell(c: str, r: list[str] = r) -> str:
            i = cols.get(c)
            return r[i] if i is not None and i < len(r) else ""

        name = cell("name").strip()
        if not name:
            raise MarkerCsvError(f"{p}:{line}: empty marker name")
        if name in names:
            raise MarkerCsvError(f"{p}:{line}: marker name {name!r} appears twice")
        names.add(name)
        lat = _num(p, line, "latitude_deg", cell("latitude_deg"))
        lon = _num(p, line, "longitude_deg", cell("longitude_deg"))
        if not -90.0 <= lat <= 90.0 or not -180.0 <= lon <= 360.0:
            raise MarkerCsvError(f"{p}:{line}: latitude/longitude out of range ({lat}, {lon})")
        sh = _num(p, line, "sigma_h_m", cell("sigma_h_m"), DEFAULT_MARKER_SIGMA_M)
        sv = _num(p, line, "sigma_v_m", cell("sigma_v_m"), DEFAULT_MARKER_SIGMA_M)
        if sh <= 0.0 or sv <= 0.0:
            raise MarkerCsvError(f"{p}:{line}: sigmas must be positive")
        out.append(
            Marker(
                name=name,
                t=_num(p, line, "time_s", cell("time_s"), math.nan),
                lat=math.radians(lat),
                lon=math.radians(lon),
                alt=_num(p, line, "altitude_m", cell("altitude_m")),
                sigma_enu=(sh, sh, sv),
            )
        )
    return markers_sorted(out)


def write_markers_csv(path: str | os.PathLike[str], markers: Iterable[Marker]) -> None:
    """Write markers (time order) as CSV: degrees with 9 decimals, metres with 4, time with 9.
    sigma_h_m is the RMS of the east and north sigmas."""
    with atomic_write(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(MARKER_COLUMNS)
        for m in markers_sorted(list(markers)):
            se, sn, su = m.sigma_enu
            w.writerow(
                [
                    m.name,
                    f"{m.t:.9f}" if math.isfinite(m.t) else "",
                    f"{math.degrees(m.lat):.9f}",
                    f"{math.degrees(m.lon):.9f}",
                    f"{m.alt:.4f}",
                    f"{math.sqrt(0.5 * (se * se + sn * sn)):.4f}",
                    f"{su:.4f}",
                ]
            )


def merge_markers(bag_markers: Sequence[Marker], csv_markers: Sequence[Marker]) -> list[Marker]:
    """The bag's markers with the CSV's added: a CSV marker replaces every bag marker of the
    same name, others are added. A CSV marker without a passage time (a survey row) takes the
    time of the bag's marker of the same name. Sorted by passage time."""
    bag_time = {m.name: m.t for m in bag_markers}
    csv_fixed = [
        dataclasses.replace(m, t=bag_time[m.name]) if math.isnan(m.t) and m.name in bag_time else m
        for m in csv_markers
    ]
    replaced = {m.name for m in csv_markers}
    kept = [m for m in bag_markers if m.name not in replaced]
    return markers_sorted([*kept, *csv_fixed])
