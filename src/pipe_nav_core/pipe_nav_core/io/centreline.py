"""The centreline CSV (INTERFACES.md) and resampling of trajectories along the chainage.

Columns (exactly, in this order)::

    time_s,distance_m,latitude_deg,longitude_deg,altitude_m,east_m,north_m,up_m,
    roll_deg,pitch_deg,azimuth_deg,sigma_east_m,sigma_north_m,sigma_up_m

time_s: header-stamp clock, s; distance_m: odometer chainage after calibration, m; latitude /
longitude: WGS84 degrees (9 decimals, 0.1 mm); altitude: ellipsoidal height, m; east/north/up:
position in ``map`` (ENU about the datum), m; roll, pitch (nose up), azimuth (clockwise from
true north, [0, 360)), degrees; sigma_*: one-sigma position uncertainty, m (empty when
unknown). Metres have 4 decimals.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.batched import lerp_rows
from pipe_nav_core.errors import CentrelineCsvError
from pipe_nav_core.geo.attitude import (
    dcm_from_quat,
    euler_from_dcm,
    quat_from_euler,
    slerp_rows,
    turn_deg,
)
from pipe_nav_core.geo.earth import (
    ecef_to_geodetic,
    geodetic_to_ecef,
    geodetic_to_enu,
    unwrapped_lon,
)
from pipe_nav_core.io.atomic import atomic_write
from pipe_nav_core.types import Datum, Trajectory

CENTRELINE_COLUMNS = [
    "time_s",
    "distance_m",
    "latitude_deg",
    "longitude_deg",
    "altitude_m",
    "east_m",
    "north_m",
    "up_m",
    "roll_deg",
    "pitch_deg",
    "azimuth_deg",
    "sigma_east_m",
    "sigma_north_m",
    "sigma_up_m",
]
CENTRELINE_HEADER = ",".join(CENTRELINE_COLUMNS)

_FORMATS = {
    "time_s": "{:.9f}",
    "latitude_deg": "{:.9f}",
    "longitude_deg": "{:.9f}",
    "roll_deg": "{:.6f}",
    "pitch_deg": "{:.6f}",
    "azimuth_deg": "{:.6f}",
}


# ----------------------------------------------------------------------------- interpolation


def interpolate_trajectory(traj: Trajectory, times: ArrayLike) -> Trajectory:
    """Trajectory at ``times`` (s, clipped to the trajectory's span): positions, velocity,
    distance and sigmas linearly in time (latitude/longitude in radians, fine at pipeline
    scales; longitude unwrapped across +-180 deg), attitude by slerp (compiled: at the 10 km
    line's 1.3 million samples a fifth of the time of whole-array arithmetic)."""
    t = np.asarray(traj.t, dtype=np.float64)
    tq = np.asarray(times, dtype=np.float64).reshape(-1)
    n = len(t)
    if n == 0:
        raise ValueError("cannot interpolate an empty trajectory")
    if n == 1:
        idx = np.zeros(len(tq), dtype=np.int64)
        return take(traj, idx)
    tq = np.clip(tq, t[0], t[-1])
    i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, n - 2)
    dt = t[i + 1] - t[i]
    f = np.where(dt > 0, (tq - t[i]) / np.where(dt > 0, dt, 1.0), 0.0)
    f = np.clip(f, 0.0, 1.0)

    def lin(a: ArrayLike | None) -> NDArray[np.float64] | None:
        if a is None:
            return None
        a = np.asarray(a, dtype=np.float64)
        rows = np.ascontiguousarray(a.reshape(n, -1))
        out = np.empty((len(tq), rows.shape[1]))
        lerp_rows(rows, i, f, out)
        return out.reshape((len(tq),) + a.shape[1:])

    lon = lin(unwrapped_lon(traj.lon))
    lon = (lon + np.pi) % (2.0 * np.pi) - np.pi
    q = np.ascontiguousarray(traj.quat_nb, dtype=np.float64).reshape(n, 4)
    quat = np.empty((len(tq), 4))
    slerp_rows(q, i, f, quat)
    return Trajectory(
        t=tq,
        lat=lin(traj.lat),
        lon=lon,
        h=lin(traj.h),
        vel_n=lin(traj.vel_n),
        quat_nb=quat,
        distance=lin(traj.distance),
        sigma_enu=lin(traj.sigma_enu),
        sigma_att=lin(traj.sigma_att),
    )


def chainage_times(t: ArrayLike, distance: ArrayLike, spacing_m: float) -> NDArray[np.float64]:
    """Times (s) at which the chainage first reaches each multiple of ``spacing_m`` within the
    run. Stops and backward creeps (distance not increasing) are skipped by following the
    running maximum of the distance."""
    t = np.asarray(t, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    if len(t) < 2:
        return t.copy()
    dm = np.maximum.accumulate(d)
    first = math.ceil(dm[0] / spacing_m)
    last = math.floor(dm[-1] / spacing_m + 1e-9)
    if last < first:
        return np.zeros(0)
    g = np.arange(first, last + 1, dtype=np.float64) * spacing_m
    j = np.searchsorted(dm, g, side="left")
    j = np.clip(j, 0, len(dm) - 1)
    out = t[j].copy()
    inner = j > 0
    jj = j[inner]
    step = dm[jj] - dm[jj - 1]
    frac = np.where(step > 0, (g[inner] - dm[jj - 1]) / np.where(step > 0, step, 1.0), 0.0)
    out[inner] = t[jj - 1] + frac * (t[jj] - t[jj - 1])
    return out


def resample_by_chainage(
    traj: Trajectory, spacing_m: float = 0.5, extra_times: Sequence[float] = ()
) -> Trajectory:
    """One sample each ``spacing_m`` of chainage (multiples of the spacing, at the time the
    distance first reaches them), plus the first and last sample and one at each of
    ``extra_times`` (marker passages; those outside the trajectory's span are ignored), in time
    order without repeated times. Interpolation: :func:`interpolate_trajectory`."""
    if spacing_m <= 0:
        raise ValueError("spacing_m must be positive")
    t = np.asarray(traj.t, dtype=np.float64)
    if len(t) == 0:
        return traj
    extra = np.asarray(list(extra_times), dtype=np.float64).reshape(-1)
    extra = extra[np.isfinite(extra) & (extra >= t[0]) & (extra <= t[-1])]
    times = np.concatenate([chainage_times(t, traj.distance, spacing_m), [t[0], t[-1]], extra])
    return interpolate_trajectory(traj, np.unique(times))


HOLE_S = 1.0  # s without a sample ...
HOLE_M = 1.0  # ... across which the position jumps more than this: a trajectory is in pieces


def pieces_of(traj: Trajectory) -> list[Trajectory]:
    """A trajectory cut where it has no sample for over HOLE_S and moves over HOLE_M across
    (segments smoothed apart across data gaps; not a stop of a centreline sampled by chainage,
    which has no sample for as long as the pig stood still)."""
    t = np.asarray(traj.t, dtype=np.float64)
    cuts = np.flatnonzero(np.diff(t) > HOLE_S)
    if len(cuts):
        lat, lon, h = (np.asarray(x, dtype=np.float64) for x in (traj.lat, traj.lon, traj.h))
        r = 6.371e6  # m: metres per radian, plenty for a metre-scale test
        step = np.sqrt(((lat[cuts + 1] - lat[cuts]) * r) ** 2
                       + ((lon[cuts + 1] - lon[cuts]) * r * np.cos(lat[cuts])) ** 2
                       + (h[cuts + 1] - h[cuts]) ** 2)  # fmt: skip
        cuts = cuts[step > HOLE_M]
    cuts = cuts + 1
    if not len(cuts):
        return [traj]
    edges = [0, *cuts.tolist(), len(traj.t)]
    return [take(traj, slice(a, b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def take(traj: Trajectory, s: slice | NDArray[np.int64]) -> Trajectory:
    """Samples ``s`` (a slice or indexes) of a trajectory."""
    return Trajectory(**{k: None if (v := getattr(traj, k)) is None else v[s]
                         for k in Trajectory.__dataclass_fields__})  # fmt: skip


def concat(trajs: list[Trajectory]) -> Trajectory:
    """Trajectories one after the other (optional fields kept only if all have them)."""

    def cat(name: str) -> np.ndarray | None:
        values = [getattr(t, name) for t in trajs]
        if any(v is None for v in values):
            return None
        return np.concatenate([np.asarray(v) for v in values])

    return Trajectory(**{name: cat(name) for name in Trajectory.__dataclass_fields__})


# ----------------------------------------------------------------------------- CSV


def centreline_columns(traj: Trajectory, datum: Datum) -> dict[str, NDArray[np.float64]]:
    """The CSV columns as arrays (degrees / metres as in the file)."""
    n = len(traj.t)
    enu = geodetic_to_enu(traj.lat, traj.lon, traj.h, datum.lat, datum.lon, datum.alt)
    enu = np.asarray(enu, dtype=np.float64).reshape(n, 3)
    roll, pitch, az = euler_from_dcm(dcm_from_quat(np.asarray(traj.quat_nb).reshape(n, 4)))
    sig = (
        np.full((n, 3), np.nan)
        if traj.sigma_enu is None
        else np.asarray(traj.sigma_enu, dtype=np.float64).reshape(n, 3)
    )
    return {
        "time_s": np.asarray(traj.t, dtype=np.float64),
        "distance_m": np.asarray(traj.distance, dtype=np.float64),
        "latitude_deg": np.degrees(traj.lat),
        "longitude_deg": np.degrees(traj.lon),
        "altitude_m": np.asarray(traj.h, dtype=np.float64),
        "east_m": enu[:, 0],
        "north_m": enu[:, 1],
        "up_m": enu[:, 2],
        "roll_deg": np.degrees(roll),
        "pitch_deg": np.degrees(pitch),
        "azimuth_deg": turn_deg(az, 6),  # as written: in [0, 360)
        "sigma_east_m": sig[:, 0],
        "sigma_north_m": sig[:, 1],
        "sigma_up_m": sig[:, 2],
    }


def centreline_text(traj: Trajectory, datum: Datum) -> str:
    """The CSV body (no header), one line per sample in time order, NaN as an empty field."""
    cols = centreline_columns(traj, datum)
    order = np.argsort(cols["time_s"], kind="stable")
    fmt = ",".join(_FORMATS.get(c, "{:.4f}") for c in CENTRELINE_COLUMNS)
    data = [cols[c][order].tolist() for c in CENTRELINE_COLUMNS]
    text = "\n".join(map(fmt.format, *data))
    # Python formats NaN as "nan"; no other field can contain those letters.
    return text.replace("nan", "") + ("\n" if text else "")


def require_finite(traj: Trajectory, what: str) -> None:
    """Raise ValueError unless every time, position, velocity, attitude and chainage of
    ``traj`` is finite: the writers' guard, so that no NaN reaches an output (sigmas may be
    NaN: unknown)."""
    cols = [traj.t, traj.lat, traj.lon, traj.h, traj.distance]
    ok = np.all([np.isfinite(np.asarray(x, dtype=np.float64)) for x in cols], axis=0)
    ok &= np.isfinite(np.asarray(traj.vel_n, dtype=np.float64)).reshape(len(ok), -1).all(axis=1)
    ok &= np.isfinite(np.asarray(traj.quat_nb, dtype=np.float64)).reshape(len(ok), -1).all(axis=1)
    if not ok.all():
        first = int(np.flatnonzero(~ok)[0])
        raise ValueError(
            f"{what}: {int((~ok).sum())} of {len(ok)} samples are not finite (the first at "
            f"{float(traj.t[first]):.3f} s): refusing to write them"
        )


def write_centreline_csv(
    path: str | os.PathLike[str], traj: Trajectory, datum: Datum, text: str | None = None
) -> None:
    """Write the centreline CSV (header row + one row per sample, sorted by time); atomic.
    About 4 microseconds per row (Python float formatting; ``text``: the body
    :func:`centreline_text` gave for traj and datum, when made already). Refuses non-finite
    samples."""
    require_finite(traj, f"{os.fspath(path)}: the centreline")
    text = centreline_text(traj, datum) if text is None else text
    with atomic_write(path, "w", newline="") as f:
        f.write(CENTRELINE_HEADER + "\n")
        f.write(text)


def _ecef_to_enu_rotation(lat: float, lon: float) -> NDArray[np.float64]:
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def datum_from_points(lat: ArrayLike, lon: ArrayLike, h: ArrayLike, enu: ArrayLike) -> Datum | None:
    """The datum whose ENU frame gives points (lat, lon rad, h m) the coordinates ``enu``:
    solved by fixed-point iteration from the point nearest the origin. None if no point is
    finite."""
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    h = np.asarray(h, dtype=np.float64)
    e = np.asarray(enu, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(h) & np.isfinite(e).all(axis=1)
    if not ok.any():
        return None
    k = int(np.flatnonzero(ok)[np.argmin(np.linalg.norm(e[ok], axis=1))])
    x_p = geodetic_to_ecef(lat[k], lon[k], h[k]).reshape(3)
    d_lat, d_lon, d_h = float(lat[k]), float(lon[k]), float(h[k])
    for _ in range(20):
        x_d = x_p - _ecef_to_enu_rotation(d_lat, d_lon).T @ e[k]
        nl, no, nh = (float(v) for v in ecef_to_geodetic(x_d))
        done = abs(nl - d_lat) < 1e-13 and abs(no - d_lon) < 1e-13 and abs(nh - d_h) < 1e-7
        d_lat, d_lon, d_h = nl, no, nh
        if done:
            break
    return Datum(d_lat, d_lon, d_h)


def read_centreline_csv(
    path: str | os.PathLike[str], warn: Callable[[str], None] | None = None
) -> tuple[Trajectory, Datum | None]:
    """Read a centreline CSV back into a Trajectory (radians; attitude from roll/pitch/azimuth;
    vel_n by differencing the ENU positions; sigma_enu None when the columns are empty) and the
    datum recovered from the ENU and geodetic columns (None if it cannot be). A last row cut
    short (a file truncated while written) is left out and ``warn`` is told; a short row
    elsewhere is an error naming its line."""
    p = os.fspath(path)
    try:
        with open(p, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except OSError as exc:
        raise CentrelineCsvError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if not rows:
        raise CentrelineCsvError(f"{p}: empty file")
    header = [c.strip() for c in rows[0]]
    missing = [c for c in CENTRELINE_COLUMNS if c not in header]
    if missing:
        raise CentrelineCsvError(f"{p}:1: missing column(s) {', '.join(missing)}")
    idx = [header.index(c) for c in CENTRELINE_COLUMNS]
    numbered = [(n + 2, r) for n, r in enumerate(rows[1:]) if r and any(x.strip() for x in r)]
    short = [n for n, r in numbered if len(r) < len(header)]
    if short and short[-1] == numbered[-1][0]:
        n, r = numbered.pop()
        short.pop()
        if warn is not None:
            warn(f"{p}:{n}: the last row is cut short ({len(r)} of {len(header)} fields): left out")
    if short:
        raise CentrelineCsvError(f"{p}:{short[0]}: fewer fields than the header names")
    data = np.full((len(numbered), len(CENTRELINE_COLUMNS)), np.nan)
    for i, (n, r) in enumerate(numbered):
        for j, k in enumerate(idx):
            s = r[k].strip()
            if s:
                try:
                    data[i, j] = float(s)
                except ValueError:
                    raise CentrelineCsvError(
                        f"{p}:{n}: {CENTRELINE_COLUMNS[j]} {s!r} is not a number"
                    ) from None
    if not len(numbered):
        raise CentrelineCsvError(f"{p}: no rows")
    c = {name: data[:, j] for j, name in enumerate(CENTRELINE_COLUMNS)}
    t = c["time_s"]
    if np.isnan(t).any():
        raise CentrelineCsvError(f"{p}: time_s must not be empty")
    lat = np.radians(c["latitude_deg"])
    lon = np.radians(c["longitude_deg"])
    enu = np.stack([c["east_m"], c["north_m"], c["up_m"]], axis=1)
    q = quat_from_euler(
        np.radians(c["roll_deg"]), np.radians(c["pitch_deg"]), np.radians(c["azimuth_deg"])
    ).reshape(-1, 4)
    sig = np.stack([c["sigma_east_m"], c["sigma_north_m"], c["sigma_up_m"]], axis=1)
    traj = Trajectory(
        t=t,
        lat=lat,
        lon=lon,
        h=c["altitude_m"],
        vel_n=_velocity(t, enu),
        quat_nb=q,
        distance=c["distance_m"],
        sigma_enu=None if np.isnan(sig).all() else sig,
    )
    return traj, datum_from_points(lat, lon, c["altitude_m"], enu)


def _velocity(t: NDArray[np.float64], enu: NDArray[np.float64]) -> NDArray[np.float64]:
    """ENU velocity by central differences over positive time steps (zeros where undefined)."""
    n = len(t)
    v = np.zeros((n, 3))
    if n < 2:
        return v
    lo = np.concatenate([[0], np.arange(n - 1)])
    hi = np.concatenate([np.arange(1, n), [n - 1]])
    dt = t[hi] - t[lo]
    good = dt > 0
    v[good] = (enu[hi[good]] - enu[lo[good]]) / dt[good, None]
    return np.nan_to_num(v)
