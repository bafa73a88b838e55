"""``RUN_welds.csv`` (INTERFACES.md, integrity products): one row per girth weld, in chainage
order, with exactly the documented columns first,

``weld,distance_m,latitude_deg,longitude_deg,altitude_m,joint_length_m,confidence,sigma_h_m,sigma_v_m``

then ``time_s`` (passage time, s of the bag clock) and ``sigma_distance_m`` (one-sigma
chainage). Latitude/longitude WGS84 degrees with 9 decimals, altitude ellipsoidal m,
``joint_length_m`` empty for the last weld, confidence 0..1 (0: filled in by the joint-length
sequence). The same text is stored in the smoothed bag as the attachment ``welds.csv``.
Written atomically; a NaN never reaches the file (only the last joint length is empty).
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Sequence

from pipe_nav_core.io.atomic import atomic_write
from pipe_nav_core.io.textfile import read_text
from pipe_nav_core.products.welds import Weld

WELD_COLUMNS = [
    "weld",
    "distance_m",
    "latitude_deg",
    "longitude_deg",
    "altitude_m",
    "joint_length_m",
    "confidence",
    "sigma_h_m",
    "sigma_v_m",
    "time_s",
    "sigma_distance_m",
]
_FMT = ["{}", "{:.4f}", "{:.9f}", "{:.9f}", "{:.4f}", "{:.4f}", "{:.3f}", "{:.4f}", "{:.4f}",
        "{:.6f}", "{:.4f}"]  # fmt: skip


def weld_row(w: Weld) -> list[object]:
    """A weld as the values of WELD_COLUMNS (degrees for people)."""
    return [w.number, w.distance, math.degrees(w.lat), math.degrees(w.lon), w.alt,
            w.joint_length, w.confidence, w.sigma_h, w.sigma_v, w.t, w.sigma_distance]  # fmt: skip


def welds_text(welds: Sequence[Weld], what: str = "welds") -> str:
    """The CSV text (header and rows) of a weld list; ValueError naming ``what`` when a value
    other than the last joint length is not finite."""
    lines = [",".join(WELD_COLUMNS)]
    for k, w in enumerate(welds):
        row = weld_row(w)
        last = k == len(welds) - 1
        bad = [
            WELD_COLUMNS[j]
            for j, v in enumerate(row[1:], 1)
            if not math.isfinite(float(v)) and not (last and j == 5)
        ]  # type: ignore[arg-type]
        if bad:
            raise ValueError(f"{what}: weld {w.number}: {', '.join(bad)} not finite: "
                             "refusing to write it")  # fmt: skip
        cells = [f.format(v) for f, v in zip(_FMT, row, strict=True)]
        if last and not math.isfinite(w.joint_length):
            cells[5] = ""
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def write_welds_csv(path: str | os.PathLike[str], welds: Sequence[Weld]) -> None:
    """Write RUN_welds.csv (atomic)."""
    text = welds_text(welds, os.fspath(path))
    with atomic_write(path, "w", newline="") as f:
        f.write(text)


def parse_welds_text(text: str, name: str = "welds.csv") -> list[Weld]:
    """Welds from RUN_welds.csv text; ``time_s`` and ``sigma_distance_m`` may be missing (NaN
    then). ValueError naming ``name``, the line and the column on bad input."""
    rows = list(csv.reader(io.StringIO(text.lstrip("\ufeff"))))
    if not rows:
        raise ValueError(f"{name}: empty file")
    header = [c.strip() for c in rows[0]]
    missing = [c for c in WELD_COLUMNS[:9] if c not in header]
    if missing:
        raise ValueError(f"{name}:1: missing column(s) {', '.join(missing)}")
    col = {c: header.index(c) for c in WELD_COLUMNS if c in header}
    out: list[Weld] = []
    for n, r in enumerate(rows[1:], 2):
        if not r or not any(x.strip() for x in r):
            continue
        if len(r) < len(header):
            raise ValueError(f"{name}:{n}: {len(r)} fields, the header names {len(header)}")
        v: dict[str, float] = {}
        for c, j in col.items():
            s = r[j].strip()
            if not s and c in ("joint_length_m", "time_s", "sigma_distance_m"):
                v[c] = math.nan
                continue
            try:
                v[c] = float(s)
            except ValueError:
                raise ValueError(f"{name}:{n}: {c} {s!r} is not a number") from None
        out.append(Weld(number=int(v["weld"]), distance=v["distance_m"],
                        t=v.get("time_s", math.nan), lat=math.radians(v["latitude_deg"]),
                        lon=math.radians(v["longitude_deg"]), alt=v["altitude_m"],
                        joint_length=v["joint_length_m"], confidence=v["confidence"],
                        sigma_h=v["sigma_h_m"], sigma_v=v["sigma_v_m"],
                        sigma_distance=v.get("sigma_distance_m", math.nan)))  # fmt: skip
    return out


def read_welds_csv(path: str | os.PathLike[str]) -> list[Weld]:
    """Read RUN_welds.csv (see :func:`parse_welds_text`)."""
    return parse_welds_text(read_text(path), os.fspath(path))


__all__ = ["WELD_COLUMNS", "parse_welds_text", "read_welds_csv", "weld_row", "welds_text",
           "write_welds_csv"]  # fmt: skip
