"""Whole-run array operations done a batch of rows at a time, with the values of doing them at
once: at field scale (10 million IMU samples over 100 km) numpy's temporaries for a whole run
are gigabytes, a batch's are megabytes."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.jit import kernel

Array = NDArray[np.float64]

BATCH = 1 << 18  # rows at a time, wherever a whole run's samples are worked through in batches


def row_norms(a: Array, batch: int = BATCH) -> Array:
    """``np.linalg.norm(a, axis=1)`` (a: (N, C), any unit: the norms are in it), the same
    values, ``batch`` rows at a time (whole, the squares of 10 million IMU samples are 0.25 GB)."""
    out = np.empty(len(a))
    for b in range(0, len(a), batch):
        out[b : b + batch] = np.linalg.norm(a[b : b + batch], axis=1)
    return out


@kernel(nogil=True)
def lerp_rows(a: Array, i: NDArray[np.int64], f: Array, out: Array) -> None:
    """out[j] (M, C) <- a[i[j]] + (a[i[j] + 1] - a[i[j]]) f[j] (a (N, C), any unit): linear
    interpolation between rows, the arithmetic of doing it with whole arrays, without their
    temporaries."""
    for j in range(i.shape[0]):
        k = i[j]
        for c in range(a.shape[1]):
            out[j, c] = a[k, c] + (a[k + 1, c] - a[k, c]) * f[j]


def gradient(f: Array, t: Array, batch: int = BATCH) -> Array:
    """``np.gradient(f, t, axis=0)`` (f: (N,) or (N, C) in any unit; t: (N,) increasing, s),
    the same values, ``batch`` rows at a time."""
    return gradient_of(lambda lo, hi: f[lo:hi], t, batch)


def gradient_of(values: Callable[[int, int], Array], t: Array, batch: int = BATCH) -> Array:
    """:func:`gradient` of the rows that ``values(lo, hi)`` gives for rows lo..hi-1, so that
    the whole array is never made (each batch asks for a row of overlap on either side).
    Zeros for a single row."""
    n = len(t)
    first = np.asarray(values(0, min(n, 1)), dtype=np.float64)
    out = np.zeros((n, *first.shape[1:]))
    if n < 2:
        return out
    dt = np.diff(t)
    uniform = bool((dt == dt[0]).all())  # as np.gradient decides: then one spacing for all
    for b in range(0, n, batch):
        e = min(b + batch, n)
        lo, hi = max(b - 1, 0), min(e + 1, n)
        out[b:e] = _gradient(np.asarray(values(lo, hi), dtype=np.float64), dt[lo : hi - 1],
                             dt[0] if uniform else None)[b - lo : e - lo]  # fmt: skip
    return out


def _gradient(f: Array, d: Array, spacing: float | None) -> Array:
    """np.gradient's arithmetic (edge_order 1) on rows f (at least two) whose time steps are
    d; spacing: the one step of a uniformly spaced run (np.gradient's uniform case)."""
    g = np.empty_like(f)
    if spacing is not None:
        g[1:-1] = (f[2:] - f[:-2]) / (2.0 * spacing)
        g[0], g[-1] = (f[1] - f[0]) / spacing, (f[-1] - f[-2]) / spacing
        return g
    shape = (-1,) + (1,) * (f.ndim - 1)
    d1, d2 = d[:-1].reshape(shape), d[1:].reshape(shape)
    w0 = -(d2) / (d1 * (d1 + d2))
    w1 = (d2 - d1) / (d1 * d2)
    w2 = d1 / (d2 * (d1 + d2))
    g[1:-1] = w0 * f[:-2] + w1 * f[1:-1] + w2 * f[2:]
    g[0], g[-1] = (f[1] - f[0]) / d[0], (f[-1] - f[-2]) / d[-1]
    return g
