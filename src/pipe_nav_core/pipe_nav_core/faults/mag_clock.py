"""The magnetometer's clock against the smoothed attitude's: measured, and taken out.

A magnetometer on a board of its own (a weld sensor's, or a driver that stamps its samples
late) puts each field sample at another time than the attitude it was measured in. The girth
welds it finds then move along the pipe by the pig's speed times the offset, every one with
full confidence: 0.3 s late at 2 m/s put the demo run's welds 0.58 m downstream (against
1 mm on time), and the movement between two runs would show it as the pipe moving.

Measured on the smoothed run (its attitude is on the IMU's clock, which
:mod:`.clock_offset` has put on the odometer's): the field the pig carries, ``B = Q vec(C_nb)
+ h`` (the weld search's fit, :mod:`pipe_nav_core.products.welds`), explains the samples best
when each is matched to the attitude at the time it was measured. The field is taken every
``BIN_S`` s of the run (interpolated between the magnetometer's samples where they are at
most ``MAX_HOLE`` sample intervals apart). For every lag within ``MAX_S``, in ``BIN_S`` steps,
each of ``BLOCKS`` stretches of the run gets its own fit (the pipe's attenuation changes along
a long run) and the fit's residual sum of squares is divided by its smallest over the lags:
a stretch where the pig turns or rolls has a sharp minimum, a straight one a flat curve that
does not pull the sum. The sum's minimum, refined by a parabola through it and its
neighbours, is the offset; its sigma is the jackknife over the stretches. An offset of
``MIN_OFFSET_S`` or more and ``SIGMAS`` of its sigma is taken out: the magnetometer's stamps
are moved onto the attitude's clock and the run is named (DEGRADED).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import fft as sp_fft

from pipe_nav_core.geo.attitude import dcm_from_quat
from pipe_nav_core.io.centreline import interpolate_trajectory
from pipe_nav_core.types import SensorLog, Trajectory

BIN_S = 0.1  # s, the field and the attitude are compared this often, and the lags' step
MAX_S = 3.0  # s, the largest offset looked for either way
BLOCKS = 16  # stretches of the run, each with its own fit (and the jackknife's pieces)
MAX_HOLE = 2.5  # magnetometer sample intervals: across a longer hole no field is taken
MIN_BINS = 40  # field samples a stretch needs (4 s)
MIN_OFFSET_S = 0.03  # s: a smaller offset is left as it is (6 cm of weld chainage at 2 m/s)
SIGMAS = 4.0  # and one within this many of its sigmas of zero

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MagClock:
    """The magnetometer's stamps minus the attitude's for the same field (s; positive: the
    magnetometer's are late), ``sigma`` its one-sigma (s), measured over ``blocks`` stretches
    of the run; ``retime``: it is to be taken out."""

    seconds: float
    sigma: float
    blocks: int
    retime: bool

    def describe(self) -> str:
        """One line for people (where it is taken out)."""
        way = "later" if self.seconds > 0 else "earlier"
        return (
            f"magnetometer clock: its stamps are {1e3 * abs(self.seconds):.0f} ms {way} than "
            f"the IMU's for the same attitude (+-{1e3 * self.sigma:.0f} ms, measured on the "
            "smoothed run): re-timed to the IMU's clock before the welds were found"
        )


def measure(log: SensorLog, centreline: Trajectory) -> MagClock | None:
    """The offset of ``log``'s magnetometer stamps from the attitude of the smoothed
    ``centreline`` (module doc), or None where the run is too short or its magnetometer too
    sparse to measure it."""
    field = _field_on_grid(log, centreline)
    if field is None:
        return None
    g, b, w = field
    at = interpolate_trajectory(centreline, g)
    x = np.empty((len(g), 10))
    x[:, :9] = dcm_from_quat(at.quat_nb).reshape(-1, 9)
    x[:, 9] = 1.0
    n = int(round(MAX_S / BIN_S))
    lags = np.arange(-n, n + 1)
    edges = np.linspace(n, len(g) - n, BLOCKS + 1).astype(np.int64)
    curves = []
    for a, e in zip(edges[:-1], edges[1:], strict=True):
        if w[a:e].sum() < MIN_BINS:
            continue
        ssr = _ssr_by_lag(x, b[a:e], w[a:e], a, lags)
        low = float(ssr.min())
        if low > 0.0 and math.isfinite(low):
            curves.append(ssr / low)
    if len(curves) < 3:
        return None
    norm = np.array(curves)
    total = norm.sum(axis=0)
    seconds = _minimum(total) * BIN_S
    jack = np.array([_minimum(total - c) * BIN_S for c in norm])
    k = len(norm)
    sigma = math.sqrt((k - 1) / k * float(np.sum((jack - jack.mean()) ** 2)))
    retime = abs(seconds) >= max(MIN_OFFSET_S, SIGMAS * sigma)
    return MagClock(seconds=float(seconds), sigma=sigma, blocks=k, retime=bool(retime))


def taken_out(log: SensorLog, centreline: Trajectory) -> tuple[SensorLog, MagClock | None]:
    """``log`` with its magnetometer re-timed where :func:`measure` finds it off (else as it
    was), and the measurement."""
    clock = measure(log, centreline)
    if clock is None or not clock.retime:
        return log, clock
    return replace(log, mag=replace(log.mag, t=log.mag.t - clock.seconds)), clock


def _field_on_grid(log: SensorLog, centreline: Trajectory) -> tuple[Array, Array, Array] | None:
    """The magnetometer's field (G, 3) T interpolated at the grid times (G,) s, BIN_S apart
    over the centreline, and each one's weight (1 where samples are on both sides within
    MAX_HOLE intervals, else 0 and the field 0); None with too few samples."""
    mt = np.asarray(log.mag.t, dtype=np.float64)
    ok = np.isfinite(log.mag.field).all(axis=1)
    if ok.sum() < MIN_BINS or len(centreline.t) < 2:
        return None
    mt, field = mt[ok], np.asarray(log.mag.field, dtype=np.float64)[ok]
    t0, t1 = float(centreline.t[0]), float(centreline.t[-1])
    size = int((t1 - t0) / BIN_S)
    if size < 2 * round(MAX_S / BIN_S) + BLOCKS * MIN_BINS:
        return None
    g = t0 + (np.arange(size) + 0.5) * BIN_S
    dt = float(np.median(np.diff(mt)))
    k = np.clip(np.searchsorted(mt, g), 1, len(mt) - 1)
    w = ((mt[k] - mt[k - 1] <= MAX_HOLE * dt) & (g >= mt[0]) & (g <= mt[-1])).astype(np.float64)
    b = np.stack([np.interp(g, mt, field[:, a]) for a in range(3)], axis=1) * w[:, None]
    return g, b, w


def _ssr_by_lag(x: Array, b: Array, w: Array, start: int, lags: NDArray[np.int64]) -> Array:
    """The residual sum of squares (per lag) of the least-squares fit of the field ``b``
    (grid rows ``start``.. of a stretch, weights ``w`` of 0 or 1) on the attitude regressors
    ``x`` of the rows ``lags`` earlier."""
    bw = b * w[:, None]
    total = float(np.sum(bw * b))
    lo = start - lags  # the first regressor row of each lag
    cross = _correlations(x[lo.min() : lo.max() + len(b)], bw)[lo - lo.min()]  # (K, 10, 3)
    gram = _grams(x, lo, len(b))
    holes = np.flatnonzero(w == 0.0)
    for i, a in enumerate(lo):  # the rows without a field sample leave the fit
        xh = x[a + holes]
        gram[i] -= xh.T @ xh
    vals, vecs = np.linalg.eigh(gram)  # the pseudo-inverse: a straight stretch's is singular
    keep = vals > 1e-10 * vals[:, -1:]
    inv = np.where(keep, 1.0 / np.where(keep, vals, 1.0), 0.0)
    proj = np.einsum("kpi,kpq->kiq", vecs, cross)  # cross in the eigenvectors' basis
    return total - np.einsum("ki,kiq->k", inv, proj**2)


def _correlations(win: Array, bw: Array) -> Array:
    """(M, 10, 3): win[m : m + len(bw)].T @ bw for every m with the window inside ``win``,
    by FFT (the lags' windows one matrix product each took most of the measurement)."""
    m = len(win) - len(bw) + 1
    size = sp_fft.next_fast_len(len(win), real=True)
    fw = sp_fft.rfft(win, size, axis=0)
    fb = np.conj(sp_fft.rfft(bw, size, axis=0))
    return sp_fft.irfft(fw[:, :, None] * fb[:, None, :], size, axis=0)[:m]


def _grams(x: Array, lo: NDArray[np.int64], size: int) -> Array:
    """(K, 10, 10): x[a : a + size].T @ x[a : a + size] for each a of ``lo``, from the sums
    over the pieces between the windows' ends (the lags' windows overlap but for the ends)."""
    ends = np.unique(np.r_[lo, lo + size])
    prefix = np.zeros((len(ends), x.shape[1], x.shape[1]))
    for k in range(1, len(ends)):
        piece = x[ends[k - 1] : ends[k]]
        prefix[k] = prefix[k - 1] + piece.T @ piece
    at = np.searchsorted(ends, lo)
    return prefix[np.searchsorted(ends, lo + size)] - prefix[at]


def _minimum(curve: Array) -> float:
    """The lag (in grid steps from the middle of ``curve``) of its minimum, refined by a
    parabola through it and its neighbours."""
    i = int(np.argmin(curve))
    frac = 0.0
    if 0 < i < len(curve) - 1:
        bend = curve[i - 1] - 2.0 * curve[i] + curve[i + 1]
        if bend > 0.0:
            frac = 0.5 * (curve[i - 1] - curve[i + 1]) / bend
    return i - (len(curve) - 1) / 2 + frac


__all__ = ["MagClock", "measure", "taken_out"]
