"""An ILI vendor's pipe tally (CSV) in, ``FEATURES.csv`` out (INTERFACES.md).

Accepted tally CSV (in the spirit of the POF pipeline-operator tally layout): a header row,
then one row per girth weld or feature, comma- or semicolon-separated (UTF-8, a BOM is fine).
Column names are matched without regard to case, spaces, underscores, brackets and units
(``Log Distance [m]`` = ``log_distance_m``); other columns are kept and passed through:

- weld number: ``weld_number``, ``weld``, ``weld_no``, ``girth_weld``, ``gw``, ``gw_number``,
  ``us_weld``, ``upstream_weld`` (on a feature row: its upstream weld);
- log distance, m (the vendor's odometer): ``log_distance_m``, ``log_distance``,
  ``odometer_m``, ``distance_m``, ``absolute_distance_m``;
- joint length, m (weld rows): ``joint_length_m``, ``joint_length``, ``pipe_length_m``,
  ``length_m``;
- distance from the upstream weld, m (feature rows): ``distance_to_us_weld_m``,
  ``distance_from_us_weld_m``, ``distance_from_weld_m``, ``us_weld_distance_m``,
  ``relative_distance_m``, ``rel_distance_m``, ``distance_to_upstream_weld_m``;
- type: ``type``, ``feature``, ``feature_type``, ``event``, ``identification``,
  ``description`` (a weld row: ``girth weld``, ``GW``, ``weld``, ``circumferential weld``);
- clock position: ``clock``, ``clock_position``, ``orientation`` (``h:mm`` or decimal hours,
  0-12).

A row is a weld row when its type says so, or (no type) when it has a weld number or a joint
length but no distance from an upstream weld. Welds need a log distance, or else every weld but
the last a joint length (the log distances are then their running sum from 0). A feature needs
its log distance, or an upstream weld and the distance from it (the upstream weld defaults to
the last weld row above it). Bad input: a ValueError naming the file, the line and the column.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from pipe_nav_core.io.atomic import all_or_none, atomic_write
from pipe_nav_core.io.textfile import read_text

if TYPE_CHECKING:
    from pipe_nav_core.products.tally import LocatedRow

ALIASES = {
    "weld": ("weldnumber", "weld", "weldno", "girthweld", "girthweldnumber", "girthweldno",
             "gw", "gwno", "gwnumber", "usweld", "upstreamweld", "usgw"),
    "log": ("logdistance", "logdist", "odometer", "distance", "absolutedistance", "absdistance"),
    "joint": ("jointlength", "pipelength", "length", "jl"),
    "rel": ("distancetousweld", "distancefromusweld", "distancefromweld", "usweldistance",
            "relativedistance", "reldistance", "distancetoupstreamweld",
            "distancetousgw", "distancefromusgw", "distancefromupstreamweld"),
    "type": ("type", "feature", "featuretype", "event", "identification", "description"),
    "clock": ("clock", "clockposition", "orientation", "clockpos"),
}  # fmt: skip
WELD_TYPES = {"girthweld", "gw", "weld", "circumferentialweld", "cw"}
LOCATED_COLUMNS = ["distance_m", "latitude_deg", "longitude_deg", "altitude_m", "sigma_h_m",
                   "sigma_v_m", "matched_weld"]  # fmt: skip
_UNITS = re.compile(r"(\[.*?\]|\(.*?\))")
_ALL = {a for names in ALIASES.values() for a in names}
_WHAT = {"clock": "a clock position (h:mm or 0-12 h)", "weld": "a weld number"}


def _norm(name: str) -> str:
    """A column name for matching: lower case, no brackets, units or separators."""
    s = re.sub(r"[^a-z0-9]", "", _UNITS.sub("", name.lower()))
    if s.endswith("m") and s[:-1] in _ALL:
        return s[:-1]
    return s


@dataclass
class TallyRow:
    """One tally row: ``line`` in the file, ``cells`` as written; ``weld``: a weld row;
    ``number``: its weld number (a feature's upstream weld; None if not given); ``log``: log
    distance m (NaN if not given); ``joint``: m; ``rel``: m from the upstream weld; ``kind``:
    the type text; ``clock``: hours 0-12 (NaN if not given)."""

    line: int
    cells: list[str]
    weld: bool
    number: int | None = None
    log: float = math.nan
    joint: float = math.nan
    rel: float = math.nan
    kind: str = ""
    clock: float = math.nan


@dataclass
class Tally:
    """A vendor tally: file name, header, rows in file order (weld rows' ``log`` filled in)."""

    path: str
    header: list[str]
    rows: list[TallyRow] = field(default_factory=list)

    def welds(self) -> list[TallyRow]:
        """The weld rows in log-distance order."""
        return sorted((r for r in self.rows if r.weld), key=lambda r: r.log)


def _clock(text: str) -> float:
    """Hours 0-12 of ``h:mm`` (12:30 = 0.5) or decimal hours."""
    m = re.fullmatch(r"(\d{1,2}):(\d{2})(?::\d{2})?", text)
    if m:
        hh, mm = int(m.group(1)), int(m.group(2))
        if hh > 12 or mm >= 60:
            raise ValueError
        return (hh % 12) + mm / 60.0
    h = float(text)
    if not (0.0 <= h <= 12.0):
        raise ValueError
    return h


def _number(text: str) -> int:
    value = float(re.sub(r"^(gw|weld)\s*", "", text.strip().lower()))
    if not value.is_integer():
        raise ValueError
    return int(value)


def parse_tally(text: str, name: str = "tally.csv") -> Tally:
    """A Tally from CSV text (module doc); ValueError naming ``name``, line and column."""
    text = text.lstrip("\ufeff")
    first = text.split("\n", 1)[0]
    delim = ";" if first.count(";") > first.count(",") else ","
    rows = list(csv.reader(io.StringIO(text), delimiter=delim))
    if not rows or not any(c.strip() for c in rows[0]):
        raise ValueError(f"{name}: empty file (no header row)")
    header = [c.strip() for c in rows[0]]
    col: dict[str, int] = {}
    for j, h in enumerate(header):
        n = _norm(h)
        for key, names in ALIASES.items():
            if n in names and key not in col:
                col[key] = j
    if "log" not in col and "joint" not in col:
        raise ValueError(f"{name}:1: no log distance or joint length column (header: "
                         f"{','.join(header)})")  # fmt: skip
    out = Tally(name, header)
    for line, r in enumerate(rows[1:], 2):
        if not r or not any(c.strip() for c in r):
            continue
        cells = [c.strip() for c in r] + [""] * max(0, len(header) - len(r))

        def get(key: str, parse, line=line, cells=cells):  # noqa: ANN001, ANN202
            j = col.get(key)
            if j is None or not cells[j]:
                return None
            try:
                return parse(cells[j])
            except ValueError:
                what = _WHAT.get(key, "a number")
                raise ValueError(f"{name}:{line}: {header[j]} {cells[j]!r} is not {what}") from None

        number, log, joint, rel = get("weld", _number), get("log", float), get("joint", float),\
            get("rel", float)  # fmt: skip
        for key, v in (("log", log), ("joint", joint), ("rel", rel)):
            if v is not None and not (math.isfinite(v) and (v >= 0 or key == "log")):
                raise ValueError(f"{name}:{line}: {header[col[key]]} {v!r} must be a finite "
                                 "distance >= 0")  # fmt: skip
        kind = cells[col["type"]] if "type" in col else ""
        typed = re.sub(r"[^a-z]", "", kind.lower())
        numbered = number is not None or joint is not None
        weld = typed in WELD_TYPES if typed else (rel is None and numbered)
        clock = get("clock", _clock)
        out.rows.append(TallyRow(line, cells[: len(header)], weld, number,
                                 math.nan if log is None else log,
                                 math.nan if joint is None else joint,
                                 math.nan if rel is None else rel, kind,
                                 math.nan if clock is None else clock))  # fmt: skip
    _fill_weld_logs(out)
    _check_features(out)
    return out


def _fill_weld_logs(t: Tally) -> None:
    welds = [r for r in t.rows if r.weld]
    if not welds:
        raise ValueError(f"{t.path}: no girth weld rows (type 'girth weld', or a weld number "
                         "without a distance to the upstream weld)")  # fmt: skip
    if all(math.isfinite(r.log) for r in welds):
        return
    given = [r for r in welds if math.isfinite(r.log)]
    if given:
        r = next(r for r in welds if not math.isfinite(r.log))
        raise ValueError(f"{t.path}:{r.line}: weld without a log distance (others have one)")
    x = 0.0
    for r in welds:
        r.log = x
        if r is not welds[-1]:
            if not math.isfinite(r.joint):
                raise ValueError(f"{t.path}:{r.line}: weld without a log distance or a joint "
                                 "length")  # fmt: skip
            x += r.joint


def _check_features(t: Tally) -> None:
    numbers = {r.number for r in t.rows if r.weld and r.number is not None}
    last: TallyRow | None = None
    for r in t.rows:
        if r.weld:
            last = r
            continue
        if r.number is not None and r.number not in numbers:
            raise ValueError(f"{t.path}:{r.line}: upstream weld {r.number} is not in the tally")
        if math.isfinite(r.rel) and r.number is None and last is not None:
            r.number = last.number
            if r.number is None:  # welds without numbers: refer to it by its log distance
                r.log = last.log + r.rel
        if not math.isfinite(r.log) and not (math.isfinite(r.rel) and r.number is not None):
            raise ValueError(f"{t.path}:{r.line}: a feature needs its log distance, or an "
                             "upstream weld and the distance from it")  # fmt: skip


def read_tally_csv(path: str | os.PathLike[str]) -> Tally:
    """Read a vendor tally CSV (module doc)."""
    return parse_tally(read_text(path), os.fspath(path))


def write_features_csv(
    path: str | os.PathLike[str], header: Sequence[str], rows: Sequence[Sequence[object]]
) -> None:
    """FEATURES.csv: the tally's own columns (``header``), then LOCATED_COLUMNS; ``rows``: the
    tally cells followed by the seven located values (floats, None for an empty field)."""
    fmt = ["{:.4f}", "{:.9f}", "{:.9f}", "{:.4f}", "{:.4f}", "{:.4f}", "{}"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*header, *LOCATED_COLUMNS])
    n = len(header)
    for r in rows:
        own, located = list(r[:n]), list(r[n:])
        for v in located:
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{os.fspath(path)}: a located value is not finite")
        cells = ["" if v is None else f.format(v) for f, v in zip(fmt, located, strict=True)]
        w.writerow(own + cells)
    with atomic_write(path, "w", newline="") as f:
        f.write(buf.getvalue())


def located_values(r: LocatedRow) -> list[object]:
    """The LOCATED_COLUMNS values of a located row (degrees; None: no matched weld)."""
    return [r.distance, math.degrees(r.lat), math.degrees(r.lon), r.alt, r.sigma_h, r.sigma_v,
            r.matched_weld]  # fmt: skip


def write_located(
    features_csv: str | os.PathLike[str] | None,
    geojson: str | os.PathLike[str] | None,
    tally: Tally,
    rows: Sequence[LocatedRow],
) -> None:
    """``pipe-nav locate``'s outputs, all or none: FEATURES.csv (:func:`write_features_csv`)
    and a GeoJSON of points with the tally's cells and the located values as properties."""
    from pipe_nav_core.io.gis import write_points_geojson

    paths = [p for p in (features_csv, geojson) if p]
    with all_or_none(paths) as staged:
        if features_csv:
            write_features_csv(staged[os.fspath(features_csv)], tally.header,
                               [[*r.row.cells, *located_values(r)] for r in rows])  # fmt: skip
        if geojson:
            points = []
            for r in rows:
                kind = "weld" if r.row.weld else "tally_feature"
                props: dict[str, object] = {"name": r.row.kind or kind, "kind": kind}
                props.update(zip(tally.header, r.row.cells, strict=False))
                props.update(zip(LOCATED_COLUMNS, located_values(r), strict=True))
                points.append((r.lat, r.lon, r.alt, props))
            write_points_geojson(staged[os.fspath(geojson)], points)


__all__ = ["LOCATED_COLUMNS", "Tally", "TallyRow", "parse_tally", "read_tally_csv",
           "located_values", "write_features_csv", "write_located"]  # fmt: skip
