"""Running statistics over a sliding window of samples, for the products' detectors.

Each window is centred on its sample and ``size`` samples long (odd); beyond the ends the
series is held at its first and last sample, as scipy.ndimage's ``mode="nearest"``, and the
results equal scipy.ndimage's ``median_filter``, ``maximum_filter1d`` and ``correlate1d`` (bit
for bit, tested). They are compiled kernels that release the GIL: scipy.ndimage costs 0.2 s to
import, more than the filter pass of a short run, and its rank filter holds the GIL for tens of
seconds on a 100 km run. Inputs are finite float64 series (a non-finite sample spoils only the
windows that hold it).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.jit import kernel

FloatArray = NDArray[np.float64]


@kernel
def _leftmost(win: FloatArray, value: float, hi: int) -> int:  # pragma: no cover - compiled
    """The first index of sorted win[:hi] whose value is not below ``value`` (hi if none)."""
    lo = 0
    while lo < hi:
        mid = (lo + hi) // 2
        if win[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


@kernel(nogil=True)
def _median(x: FloatArray, size: int) -> FloatArray:  # pragma: no cover - compiled
    n = x.shape[0]
    h = size // 2
    out = np.empty(n)
    if n == 0:
        return out
    win = np.empty(size)
    for j in range(size):
        win[j] = x[min(max(j - h, 0), n - 1)]
    win.sort()
    out[0] = win[h]
    for i in range(1, n):
        old = x[min(max(i - 1 - h, 0), n - 1)]
        new = x[min(i + h, n - 1)]
        p = _leftmost(win, old, size - 1)  # where old is (clipped: never past the window)
        q = _leftmost(win, new, size)  # where new goes
        if q > p:
            for j in range(p, q - 1):
                win[j] = win[j + 1]
            win[q - 1] = new
        else:
            for j in range(p, q, -1):
                win[j] = win[j - 1]
            win[q] = new
        out[i] = win[h]
    return out


@kernel(nogil=True)
def _maximum(x: FloatArray, size: int) -> FloatArray:  # pragma: no cover - compiled
    n = x.shape[0]
    h = size // 2
    out = np.empty(n)
    queue = np.empty(n, dtype=np.int64)  # indices of a decreasing run of values
    head = 0
    tail = 0
    for i in range(n + h):
        if i < n:
            while tail > head and x[queue[tail - 1]] <= x[i]:
                tail -= 1
            queue[tail] = i
            tail += 1
        c = i - h
        if c >= 0:
            while queue[head] < c - h:
                head += 1
            out[c] = x[queue[head]]
    return out


@kernel(nogil=True)
def _correlate_symmetric(x: FloatArray, weights: FloatArray) -> FloatArray:  # pragma: no cover
    n = x.shape[0]
    h = weights.shape[0] // 2
    out = np.empty(n)
    for i in range(n):
        s = x[i] * weights[h]
        for j in range(-h, 0):
            s += (x[min(max(i + j, 0), n - 1)] + x[min(i - j, n - 1)]) * weights[h + j]
        out[i] = s
    return out


def _odd(size: int) -> int:
    if size < 1 or size % 2 == 0:
        raise ValueError(f"the window must be an odd number of samples, not {size}")
    return int(size)


def running_median(x: FloatArray, size: int) -> FloatArray:
    """The median of each ``size``-sample window (odd) of a series or of each column of an
    (N, C) array; the same units as x."""
    size = _odd(size)
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1:
        return _median(np.ascontiguousarray(a), size)
    return np.column_stack([_median(np.ascontiguousarray(c), size) for c in a.T])


def running_maximum(x: FloatArray, size: int) -> FloatArray:
    """The largest sample of each ``size``-sample window (odd) of a series."""
    return _maximum(np.ascontiguousarray(x, dtype=np.float64), _odd(size))


def correlate(x: FloatArray, weights: FloatArray) -> FloatArray:
    """Each sample's window times ``weights`` (odd length, symmetric about its middle), summed:
    a series or each column of an (N, C) array filtered by a symmetric (zero-phase) kernel."""
    w = np.ascontiguousarray(weights, dtype=np.float64)
    _odd(len(w))
    if not np.array_equal(w, w[::-1]):
        raise ValueError("correlate: the weights must be symmetric about their middle")
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1:
        return _correlate_symmetric(np.ascontiguousarray(a), w)
    return np.column_stack([_correlate_symmetric(np.ascontiguousarray(c), w) for c in a.T])
