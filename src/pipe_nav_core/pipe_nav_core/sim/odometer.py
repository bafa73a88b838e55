"""Wheel odometer: a wheel rolling on the pipe wall, counted in ticks.

The wheel's contact point is body-fixed at lever arm d (m, base_link), e.g. (0, 0, -D/2) for a
wheel on the bottom of the pig. It rolls along the wall at

    wall speed = v_x^b + (omega_eb^b x d)_x,

so in a bend it reads more on the outer wall and less on the inner one, and a rolling pig moves
the wheel round the wall. The reading is ``floor(wall distance * (1 + scale) * slip / tick) * tick``
where ``slip`` collects brief wheel stalls (reading less) and spins (reading more). The speed field
is what a driver computes from the counts: difference of the counted distance over a window.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.types import OdometerSamples

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SlipEpisode:
    """Wheel slip from t_start to t_end (s): the wheel reads (1 + factor) times the true wall
    distance in between; factor -1 = full stall, -0.5 = half, +0.3 = spinning 30 % fast."""

    t_start: float
    t_end: float
    factor: float


def draw_slips(
    rng: np.random.Generator,
    t_begin: float,
    t_end: float,
    mean_interval: float,
    duration: tuple[float, float],
    stall_fraction: float = 0.7,
    spin_max: float = 0.5,
) -> list[SlipEpisode]:
    """Random slip episodes over [t_begin, t_end] s, about one every ``mean_interval`` s, each
    lasting U(duration) s; a fraction ``stall_fraction`` are stalls (factor U(-1, -0.3)), the
    rest spins (factor U(0.1, spin_max)). Episodes do not overlap. Empty if mean_interval <= 0."""
    out: list[SlipEpisode] = []
    if mean_interval <= 0.0:
        return out
    t = t_begin + rng.exponential(mean_interval)
    while t < t_end:
        d = rng.uniform(*duration)
        stall = rng.random() < stall_fraction
        f = -rng.uniform(0.3, 1.0) if stall else rng.uniform(0.1, spin_max)
        out.append(SlipEpisode(t, min(t + d, t_end), f))
        t += d + rng.exponential(mean_interval)
    return out


def slip_integral(t: FloatArray, slips: Sequence[SlipEpisode]) -> FloatArray:
    """Cumulative slip time-weight Phi(t) = sum over episodes of factor * |[t_start, t] and
    episode| (s); differences over an interval give factor * overlap."""
    t = np.asarray(t, dtype=np.float64)
    if not slips:
        return np.zeros(t.shape)
    bp = np.array([[e.t_start, e.t_end] for e in slips]).reshape(-1)
    val = np.zeros(bp.shape)
    acc = 0.0
    for i, e in enumerate(slips):
        val[2 * i] = acc
        acc += e.factor * (e.t_end - e.t_start)
        val[2 * i + 1] = acc
    return np.interp(t, bp, val, left=0.0, right=acc)


def odometer_reading(
    t: FloatArray,
    wall_distance: FloatArray,
    *,
    scale_error: float,
    tick: float,
    slips: Sequence[SlipEpisode],
    speed_window: float,
) -> OdometerSamples:
    """Odometer samples at times t (s) from the true cumulative wall distance (m) there.

    scale_error: true relative scale error of the wheel (dimensionless); tick: m per count
    (0 = unquantised); slips: episodes; speed_window: s, the driver's speed is the counted
    distance difference over this window (at least one sample).
    Returns distance (m, since the first sample) and speed (m/s).
    """
    t = np.asarray(t, dtype=np.float64)
    w = np.asarray(wall_distance, dtype=np.float64)
    n = len(t)
    if n == 0:
        return OdometerSamples(t, w, w)
    dw = np.diff(w, prepend=w[0])
    if slips:
        dt = np.diff(t, prepend=t[0])
        phi = slip_integral(t, slips)
        frac = np.divide(np.diff(phi, prepend=phi[0]), dt, out=np.zeros(n), where=dt > 0)
        dw = dw * (1.0 + frac)
    raw = np.cumsum(dw * (1.0 + scale_error))
    dist = np.floor(raw / tick + 1e-9) * tick if tick > 0.0 else raw
    rate = (n - 1) / (t[-1] - t[0]) if n > 1 else 1.0
    k = max(1, int(round(speed_window * rate)))
    speed = np.zeros(n)
    if n > 1:
        j = np.maximum(np.arange(n) - k, 0)
        span = t - t[j]
        speed = np.divide(dist - dist[j], span, out=np.zeros(n), where=span > 0)
    return OdometerSamples(t, dist, speed)
