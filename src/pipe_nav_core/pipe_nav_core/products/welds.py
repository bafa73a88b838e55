"""Girth welds seen by the magnetometer (and the wheel's jolt on the weld bead); the alignment
of two weld lists by their joint lengths is :mod:`.joints`.

Detection (:func:`detect_welds`), on the smoothed centreline of the run:

1. Every magnetometer sample (imu_link, T) gets the smoothed attitude and chainage of its time.
   The field the pig carries along is removed by a least-squares fit of
   ``B = Q vec(C_nb) + h`` over the run (Q: 3 x 9, the Earth field as the pipe attenuates it seen
   through the attitude and the IMU mount; h: the pig's hard iron), so no mount, field or hard
   iron needs to be known; the fit is repeated twice without the samples near the welds found
   (their anomalies would otherwise leak into it and show, during fast roll turns, as false
   welds). The residual is rotated into ENU (``C_nb R_bi``), averaged into bins
   of ``GRID_STEP_M`` of chainage, and what still varies slowly (attitude errors, a hard iron or
   attenuation that drifts along the run) is taken out by a running median over
   ``BASELINE_M``.
2. A matched filter along chainage: each ENU axis correlated with a zero-mean Gaussian of the
   weld anomaly's width (``width_d`` pipe diameters, one sigma), normalized by its robust
   (MAD) noise, the three squared and summed (the anomaly's direction is unknown): ``snr`` is
   the square root, about 1.7 on noise alone. Peaks over ``threshold`` at least
   ``MIN_SEPARATION_D`` diameters apart are welds; the chainage is refined by a parabola through
   the peak and its neighbours.
3. Where the IMU shows the wheel's jolt on the bead (a short vertical specific-force spike, see
   sim/weld_bump.py), a weak magnetic peak (over ``weak``) within ``JOLT_MATCH_M`` of a jolt is
   a weld as well.
4. The joint-length sequence cleans the list: with the typical (median) joint length L, a weld
   splitting a joint of about L into two short pieces (within ``JOINT_TOLERANCE``) is dropped
   when it is among the weaker half; a joint of about n L (n >= 2) gets the n - 1 welds it
   misses: the strongest weak peak (over ``weak``) near each expected chainage, else a weld
   filled in at the expected chainage with confidence 0.

Sigmas: ``sigma_distance`` combines the peak's localisation (width sqrt(2) / snr, at least the
bin's; in a bend also width times the angle the axis turns within one width) with the
centreline's position sigma along the pipe axis; ``sigma_h``/``sigma_v`` are the centreline's
sigma_enu at the weld (horizontal: sqrt(east^2 + north^2)) plus the localisation error
projected by the pipe's pitch. Confidence: snr / (2 threshold), at most 1 (0.5 at the
threshold; 0 for a filled-in weld).

"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core import batched
from pipe_nav_core.geo.attitude import body_x_axis, dcm_from_quat
from pipe_nav_core.io.centreline import interpolate_trajectory
from pipe_nav_core.memory import file_array, let_go
from pipe_nav_core.products.windows import correlate, running_maximum, running_median
from pipe_nav_core.smooth import logs
from pipe_nav_core.types import Datum, ImuSamples, SensorLog, Trajectory

FloatArray = NDArray[np.float64]

GRID_STEP_M = 0.05  # m, chainage bins of the magnetometer residual
# regressors larger than this wait in a file between the fits (0.2 GB at 100 km, whose fits
# without the welds' samples held them beside their own copy and LAPACK's)
MAPPED_X_BYTES = 64 << 20
FIT_COND_MAX = 1e8  # condition number of the field fit's normal equations solved as they are
BASELINE_M = 3.0  # m, running-median window of the slowly varying residual
WIDTH_D = 1.0  # weld anomaly width (one sigma) in pipe diameters
THRESHOLD_SNR = 6.0  # a weld on its own
WEAK_SNR = 4.0  # a weld where the joint sequence or a jolt expects one
MIN_SEPARATION_D = 5.0  # pipe diameters between two welds, at least 1 m
JOINT_TOLERANCE = 0.15  # relative tolerance of a joint length against the typical one
JOLT_MATCH_M = 0.5  # m, a jolt and a weak magnetic peak this close are one weld
JOLT_SNR = 8.0  # robust sigmas of the vertical specific-force spike
JOLT_BASELINE_S = 0.3  # s, running-median baseline of the vertical specific force


@dataclass
class Weld:
    """One girth weld. number 1.. in chainage order; distance: chainage m (the centreline's
    distance_m); t: passage time s (bag clock); lat, lon rad, alt m (WGS84, on the
    centreline); joint_length: m to the next weld (NaN for the last); confidence 0..1 (0: filled
    in by the joint-length sequence); sigma_h, sigma_v: m one-sigma horizontal and vertical
    position; sigma_distance: m one-sigma chainage."""

    number: int
    distance: float
    t: float
    lat: float
    lon: float
    alt: float
    joint_length: float
    confidence: float
    sigma_h: float
    sigma_v: float
    sigma_distance: float


@dataclass
class _Candidate:
    distance: float
    snr: float
    sigma_loc: float
    filled: bool = False


def _monotone_distance(traj: Trajectory) -> tuple[FloatArray, FloatArray]:
    """(t, chainage made non-decreasing) of a trajectory, for chainage <-> time."""
    return np.asarray(traj.t, dtype=np.float64), np.maximum.accumulate(
        np.asarray(traj.distance, dtype=np.float64)
    )


def _binned(d: FloatArray, values: FloatArray, step: float) -> tuple[FloatArray, FloatArray]:
    """(grid chainages, (G, 3) bin means) of values at chainages d; empty bins interpolated."""
    d0 = float(d.min())
    idx = np.rint((d - d0) / step).astype(np.int64)
    n = int(idx.max()) + 1
    count = np.bincount(idx, minlength=n).astype(np.float64)
    grid = d0 + step * np.arange(n)
    out = np.empty((n, values.shape[1]))
    full = count > 0
    for a in range(values.shape[1]):
        mean = np.bincount(idx, weights=values[:, a], minlength=n)[full] / count[full]
        out[:, a] = np.interp(grid, grid[full], mean)
    return grid, out


def _robust_sigma(x: FloatArray) -> float:
    dev = x - np.median(x)
    s = 1.4826 * float(np.median(np.abs(dev, out=dev)))
    return s if s > 0 else float(np.std(x)) or 1.0


class _MagSamples(NamedTuple):
    """The magnetometer samples within the centreline, as the field fit takes them: field
    ``b`` (M, 3) T imu_link, the fit's regressors ``x`` (M, 10: C_nb at their times, row by
    row, and 1; over MAPPED_X_BYTES in a file, :mod:`pipe_nav_core.memory`, in memory only
    while a fit reads them) and chainage ``d`` (M,) m (non-decreasing)."""

    b: FloatArray
    x: FloatArray
    d: FloatArray


def _mag_samples(log: SensorLog, centreline: Trajectory) -> _MagSamples | None:
    """The samples of the fit (once per run: each fit leaves out other welds, not samples),
    None with fewer than 20 within the centreline."""
    t_c = np.asarray(centreline.t, dtype=np.float64)
    mt = np.asarray(log.mag.t, dtype=np.float64)
    keep = (mt >= t_c[0]) & (mt <= t_c[-1]) & np.isfinite(log.mag.field).all(axis=1)
    if keep.sum() < 20:
        return None
    b = np.asarray(log.mag.field, dtype=np.float64)
    if not keep.all():  # else the log's own samples (not copied: 0.06 GB at 100 km)
        b, mt = b[keep], mt[keep]
    x, d = file_array((len(b), 10), MAPPED_X_BYTES), np.empty(len(b))
    for a in range(0, len(b), batched.BATCH):  # in batches: the centreline's columns at the
        s = slice(a, a + batched.BATCH)  # 2.6 million samples of 100 km took 0.35 GB at once
        at = interpolate_trajectory(centreline, mt[s])
        x[s, :9] = dcm_from_quat(at.quat_nb).reshape(-1, 9)
        x[s, 9] = 1.0
        d[s] = at.distance
    let_go(x)
    return _MagSamples(b, x, np.maximum.accumulate(d))


def mag_residual(
    log: SensorLog,
    centreline: Trajectory,
    r_base_imu: ArrayLike | None = None,
    exclude: ArrayLike = (),
    exclude_half: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """The magnetometer field left once what the pig carries along is removed (module doc,
    step 1): (grid chainages m, (G, 3) residual T in ENU), ``GRID_STEP_M`` apart. The samples
    within ``exclude_half`` m of the chainages ``exclude`` (welds found already) are left out
    of the fit, so that their anomalies do not leak into it."""
    return _residual(_mag_samples(log, centreline), r_base_imu, exclude, exclude_half)


def _field_fit(x: FloatArray, b: FloatArray) -> FloatArray:
    """(10, 3) least-squares coefficients of ``b`` (M, 3) on the regressors ``x`` (M, 10):
    through the normal equations (a tenth of the SVD's time on 0.3 M samples) while they are
    well conditioned, which a run that turns and rolls makes them; else the SVD solution with
    the near-null directions left out (a pig that never turns: its C_nb columns are nearly
    collinear with the constant)."""
    gram = x.T @ x
    if np.linalg.cond(gram) < FIT_COND_MAX:
        return np.linalg.solve(gram, x.T @ b)
    coef, *_ = np.linalg.lstsq(x, b, rcond=1e-9)
    return coef


def _residual(
    m: _MagSamples | None,
    r_base_imu: ArrayLike | None = None,
    exclude: ArrayLike = (),
    exclude_half: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """:func:`mag_residual` of the samples ``m``."""
    if m is None:
        return np.empty(0), np.empty((0, 3))
    b, x, d = m
    c_nb = x[:, :9].reshape(-1, 3, 3)  # a view of the regressors
    fit = np.ones(len(b), dtype=bool)
    ex = np.sort(np.asarray(exclude, dtype=np.float64).reshape(-1))
    if len(ex) and exclude_half > 0:
        k = np.clip(np.searchsorted(ex, d), 0, len(ex) - 1)
        near = np.minimum(np.abs(d - ex[k]), np.abs(d - ex[np.maximum(k - 1, 0)]))
        fit = near > exclude_half
    whole = bool(fit.all())  # then no copies of the regressors (0.2 GB at 100 km)
    x_fit = x if whole else x[fit]
    if not whole:
        let_go(x)  # (from its file) while the fit runs on its copy of the rows it takes
    coef = _field_fit(x_fit, b if whole else b[fit])
    del x_fit
    res_i = b - x @ coef
    r_bi = np.eye(3) if r_base_imu is None else np.asarray(r_base_imu, dtype=np.float64)
    res_n = np.empty_like(res_i)
    for a in range(0, len(b), batched.BATCH):  # in batches: bounded temporaries
        s = slice(a, a + batched.BATCH)  # C_nb (R_bi r): a quarter the time of (C_nb R_bi) r
        res_n[s] = np.einsum("kij,kj->ki", c_nb[s], res_i[s] @ r_bi.T)
    let_go(x)
    grid, res = _binned(d, res_n, GRID_STEP_M)
    size = max(3, int(round(BASELINE_M / GRID_STEP_M)) | 1)
    base = running_median(res, size)
    return grid, res - base


def mag_snr(residual: FloatArray, width: float, step: float = GRID_STEP_M) -> FloatArray:
    """The matched-filter statistic (module doc, step 2) of an ENU residual on a chainage grid
    ``step`` m apart, for an anomaly ``width`` m wide (one sigma)."""
    half = max(2, int(math.ceil(3.0 * width / step)))
    x = np.arange(-half, half + 1) * step
    g = np.exp(-0.5 * (x / width) ** 2)
    g -= g.mean()
    g /= np.linalg.norm(g)
    y = correlate(residual, g)
    z2 = sum((y[:, a] / _robust_sigma(y[:, a])) ** 2 for a in range(y.shape[1]))
    return np.sqrt(z2)


def jolt_deviation(imu: ImuSamples, r_base_imu: ArrayLike | None = None) -> FloatArray:
    """(N,) per IMU sample, the vertical specific force (base_link z, m/s^2) less its
    ``JOLT_BASELINE_S`` running median (which follows the pig's roll and surges): where
    :func:`jolt_chainages` looks for the wheel's jolts. From the IMU alone, so that it can be
    found while the run is still being smoothed."""
    r_bi = np.eye(3) if r_base_imu is None else np.asarray(r_base_imu, dtype=np.float64)
    az = np.asarray(imu.accel, dtype=np.float64) @ r_bi[2]
    logs.let_go(imu)  # read from a file (smooth.logs.map_imu): 0.33 GB at 100 km, read again
    if len(az) < 2:  # no sample interval
        return az
    size = max(3, int(round(JOLT_BASELINE_S / float(np.median(np.diff(imu.t))))) | 1)
    return np.subtract(az, running_median(az, size), out=az)


def jolt_chainages(
    log: SensorLog,
    centreline: Trajectory,
    r_base_imu: ArrayLike | None = None,
    threshold: float = JOLT_SNR,
    min_separation: float = 1.0,
    deviation: FloatArray | None = None,
) -> FloatArray:
    """Chainages (m) where the vertical specific force spikes over ``threshold`` robust sigmas
    of its :func:`jolt_deviation` (``deviation``, when found before: used up) while the pig
    moves: the wheel on a weld bead (a jolt at rest is not a weld)."""
    imu = log.imu
    t_c, d_c = _monotone_distance(centreline)
    if len(imu.t) < 10 or len(t_c) < 2:
        return np.empty(0)
    dev = jolt_deviation(imu, r_base_imu) if deviation is None else deviation
    dt = float(np.median(np.diff(imu.t)))
    d = np.interp(imu.t, t_c, d_c)
    speed = batched.gradient(d, imu.t)  # np.gradient's values, without its temporaries
    moving = (speed > 0.05) & (imu.t > t_c[0]) & (imu.t < t_c[-1])
    del speed
    if moving.sum() < 10:
        return np.empty(0)
    sigma = _robust_sigma(dev[moving])
    z = np.abs(dev, out=dev)  # |dev| / sigma, in dev's memory
    z /= sigma
    z[~moving] = 0.0
    peaks = _peaks(z, height=threshold, distance=max(1, int(round(0.2 / dt))))
    out: list[float] = []
    for k in peaks:
        if not out or d[k] - out[-1] >= min_separation:
            out.append(float(d[k]))
    return np.asarray(out)


def _peaks(x: FloatArray, height: float, distance: int) -> NDArray[np.int64]:
    """Indices of the samples of x at least ``height`` that are the largest within
    +-``distance`` samples (the first of a plateau): scipy.signal.find_peaks(x, height,
    distance) but for a lower peak beside a removed one."""
    top = running_maximum(x, 2 * distance + 1)
    rising = x > np.r_[-np.inf, x[:-1]]
    return np.flatnonzero((x >= height) & (x == top) & rising)


def _refine(grid: FloatArray, snr: FloatArray, k: int) -> float:
    """Chainage of the peak at bin k by a parabola through it and its neighbours."""
    if 0 < k < len(snr) - 1:
        a, b, c = snr[k - 1], snr[k], snr[k + 1]
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den < 0 else 0.0
        return float(grid[k] + np.clip(off, -0.5, 0.5) * (grid[1] - grid[0]))
    return float(grid[k])


def _candidate(grid: FloatArray, snr: FloatArray, k: int, width: float) -> _Candidate:
    step = float(grid[1] - grid[0]) if len(grid) > 1 else GRID_STEP_M
    loc = max(math.sqrt(2.0) * width / max(float(snr[k]), 1e-6), step / math.sqrt(12.0))
    return _Candidate(_refine(grid, snr, k), float(snr[k]), loc)


def _strongest_near(grid: FloatArray, snr: FloatArray, centre: float, half: float, weak: float,
                    width: float) -> _Candidate | None:  # fmt: skip
    """The strongest local peak over ``weak`` within ``half`` m of ``centre``, or None."""
    a, b = np.searchsorted(grid, [centre - half, centre + half])
    if b - a < 3:
        return None
    k = a + int(np.argmax(snr[a:b]))
    if snr[k] < weak or k in (a, b - 1):
        return None
    return _candidate(grid, snr, k, width)


def clean_by_joints(
    cands: list[_Candidate],
    grid: FloatArray,
    snr: FloatArray,
    *,
    width: float,
    weak: float = WEAK_SNR,
    tolerance: float = JOINT_TOLERANCE,
) -> list[_Candidate]:
    """The weld list cleaned by the joint-length sequence (module doc, step 4)."""
    cands = sorted(cands, key=lambda c: c.distance)
    if len(cands) < 4:
        return cands
    typical = float(np.median(np.diff([c.distance for c in cands])))
    if not typical > 0:
        return cands
    # extras: a weak weld splitting a joint of about the typical length
    # (the welds left are a linked list over the sorted ones: a weld's neighbours are found
    # and it is taken out in constant time, at 100 km as at 1 km)
    median_snr = float(np.median([c.snr for c in cands]))
    n_c = len(cands)
    before, after = list(range(-1, n_c - 1)), list(range(1, n_c + 1))
    removed = [False] * n_c
    for k in sorted(range(n_c), key=lambda i: cands[i].snr):
        c = cands[k]
        if c.snr >= median_snr:
            break
        a, b = before[k], after[k]
        if a < 0 or b == n_c:  # the first or the last weld left
            continue
        l1 = c.distance - cands[a].distance
        l2 = cands[b].distance - c.distance
        short = max(l1, l2) < (1.0 - tolerance) * typical
        if short and abs(l1 + l2 - typical) <= tolerance * typical:
            removed[k] = True
            after[a], before[b] = b, a
    cands = [c for c, gone in zip(cands, removed, strict=True) if not gone]
    # misses: a joint of n typical lengths gets its n - 1 welds
    out = [cands[0]]
    for nxt in cands[1:]:
        prev = out[-1]
        length = nxt.distance - prev.distance
        n = int(round(length / typical))
        if n >= 2 and abs(length - n * typical) <= tolerance * n * typical:
            for m in range(1, n):
                expect = prev.distance + m * length / n
                found = _strongest_near(grid, snr, expect, tolerance * typical, weak, width)
                out.append(found or _Candidate(expect, 0.0, 0.5 * tolerance * typical, True))
        out.append(nxt)
    return out


def detect_welds(
    log: SensorLog,
    centreline: Trajectory,
    datum: Datum,
    *,
    pipe_diameter: float = 0.2,
    r_base_imu: ArrayLike | None = None,
    width_d: float = WIDTH_D,
    threshold: float = THRESHOLD_SNR,
    weak: float = WEAK_SNR,
    use_jolts: bool = True,
    clean: bool = True,
    jolts: FloatArray | None = None,
) -> list[Weld]:
    """The girth welds of a run (module doc) from its sensor log (``log.mag`` in imu_link, T;
    ``log.imu`` for the jolts) and its smoothed ``centreline`` (attitude, chainage, sigma_enu
    at the IMU rate or finer). pipe_diameter: m (the anomaly's width is ``width_d`` of it);
    r_base_imu: (3, 3) imu_link -> base_link (identity when None); threshold, weak: snr of a
    weld on its own and of one the joint sequence or a jolt expects; use_jolts: look for the
    wheel's jolts in the IMU (``jolts``: their :func:`jolt_deviation`, when found before);
    clean: apply the joint-length sequence. ``datum`` is the run's
    (the welds are given in WGS84, so it is not needed for the positions). [] when the log has
    no magnetometer samples within the centreline."""
    del datum  # positions come from the centreline's own geodetic coordinates
    if len(log.mag.t) == 0 or len(centreline.t) < 2:
        return []
    width = max(float(width_d) * float(pipe_diameter), 2.0 * GRID_STEP_M)
    sep = max(1.0, MIN_SEPARATION_D * float(pipe_diameter))
    apart = max(1, int(round(sep / GRID_STEP_M)))
    samples = _mag_samples(log, centreline)
    grid, residual = _residual(samples, r_base_imu)
    if len(grid) < 10:
        return []
    for _ in range(2):  # the second time with the welds found left out of the field's fit
        snr = mag_snr(residual, width)
        peaks = _peaks(snr, height=threshold, distance=apart)
        if not len(peaks):
            break
        grid, residual = _residual(samples, r_base_imu, grid[peaks], 4.0 * width)
    del samples  # 0.3 GB at 100 km, not needed by the jolt check
    snr = mag_snr(residual, width)
    peaks = _peaks(snr, height=threshold, distance=apart)
    cands = [_candidate(grid, snr, int(k), width) for k in peaks]
    if use_jolts and len(log.imu.t):
        have = np.array([c.distance for c in cands])
        for s in jolt_chainages(log, centreline, r_base_imu, min_separation=sep, deviation=jolts):
            if len(have) and np.min(np.abs(have - s)) < sep:
                continue
            found = _strongest_near(grid, snr, s, JOLT_MATCH_M, weak, width)
            if found is not None:
                cands.append(found)
    if clean:
        cands = clean_by_joints(cands, grid, snr, width=width, weak=weak)
    return _welds_of(sorted(cands, key=lambda c: c.distance), centreline, threshold, width)


def _axis_turn(centreline: Trajectory, t_c: FloatArray, d_c: FloatArray, dist: FloatArray,
               half: float) -> FloatArray:  # fmt: skip
    """Angle (rad) the pipe axis turns between dist - half and dist + half (m)."""
    ends = [interpolate_trajectory(centreline, np.interp(dist + k * half, d_c, t_c))
            for k in (-1.0, 1.0)]  # fmt: skip
    a, b = (body_x_axis(e.quat_nb) for e in ends)
    return np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0))


def _welds_of(
    cands: list[_Candidate], centreline: Trajectory, threshold: float, width: float
) -> list[Weld]:
    """The candidates as Welds: time, position and sigmas from the centreline. In a bend the
    field the pig carries turns with it within the anomaly's width, and what the field model
    leaves of it shifts the peak: measured at 0.2 m in a 45 deg elbow of 0.6 m radius. The
    localisation sigma gets width times the angle the axis turns within +- width."""
    if not cands:
        return []
    t_c, d_c = _monotone_distance(centreline)
    dist = np.array([c.distance for c in cands])
    t = np.interp(dist, d_c, t_c)
    at = interpolate_trajectory(centreline, t)
    n = len(cands)
    sig = np.zeros((n, 3)) if at.sigma_enu is None else np.asarray(at.sigma_enu).reshape(n, 3)
    sig = np.nan_to_num(sig.astype(np.float64))
    axis = body_x_axis(at.quat_nb)  # base_link x (along the pipe) in ENU
    along = np.sqrt(np.sum((axis * sig) ** 2, axis=1))
    turn = _axis_turn(centreline, t_c, d_c, dist, width)
    loc = np.hypot([c.sigma_loc for c in cands], width * turn)
    horiz = np.hypot(axis[:, 0], axis[:, 1])
    sigma_h = np.sqrt(sig[:, 0] ** 2 + sig[:, 1] ** 2 + (loc * horiz) ** 2)
    sigma_v = np.sqrt(sig[:, 2] ** 2 + (loc * axis[:, 2]) ** 2)
    sigma_d = np.sqrt(loc**2 + along**2)
    joints = np.append(np.diff(dist), np.nan)
    return [
        Weld(
            number=k + 1,
            distance=float(dist[k]),
            t=float(t[k]),
            lat=float(at.lat[k]),
            lon=float(at.lon[k]),
            alt=float(at.h[k]),
            joint_length=float(joints[k]),
            confidence=0.0 if c.filled else float(min(1.0, c.snr / (2.0 * threshold))),
            sigma_h=float(sigma_h[k]),
            sigma_v=float(sigma_v[k]),
            sigma_distance=float(sigma_d[k]),
        )  # fmt: skip
        for k, c in enumerate(cands)
    ]


__all__ = [
    "Weld",
    "clean_by_joints",
    "detect_welds",
    "jolt_chainages",
    "mag_residual",
    "mag_snr",
]
