"""The odometer encoder's resolution (m per count): configured, or learnt from the readings.

The resolution sets the quantization noise of the odometer speed and the prior of the
quantization error states. Unconfigured (0), it is the smallest nonzero step between
successive readings seen so far, learnt as the readings arrive; the value at a time depends
only on the readings up to it, not on how the input was batched.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.types import OdometerSamples

Array = NDArray[np.float64]

FLOOR_M = 1e-4  # m: the resolution used is never below this


class OdometerResolution:
    """The encoder resolution of one pass. configured: m per count, 0 to learn it."""

    def __init__(self, configured: float) -> None:
        self.configured = configured
        self.value = configured  # m: in use, configured or learnt so far (0 = none yet)
        self._last: float | None = None  # m: the last reading learnt from
        self._learnt_t = -math.inf  # s: its stamp

    def at(self, odo: OdometerSamples, t_now: float) -> float:
        """The resolution (m) used in the noise model at t_now (s), floored at FLOOR_M, from
        the buffered readings odo."""
        return float(self.at_times(odo, np.array([t_now]))[0])

    def at_times(self, odo: OdometerSamples, t_now: Array) -> Array:
        """:meth:`at` at each of the increasing times t_now (s); learns from the readings up
        to the last of them."""
        if self.configured > 0.0:
            return np.full(len(t_now), max(self.configured, FLOOR_M))
        o = odo
        i0 = int(np.searchsorted(o.t, self._learnt_t, side="right"))
        upto = np.searchsorted(o.t, t_now, side="right") - i0  # readings learnt from per time
        quantum = self.value if self.value > 0.0 else math.inf
        if upto[-1] <= 0:
            return np.full(len(t_now), max(self.value, FLOOR_M))
        dist = o.distance[i0 : i0 + upto[-1]]
        prev = self._last
        d = (
            np.abs(_increments(prev, dist))
            if prev is not None
            else np.abs(np.diff(dist, prepend=dist[0]))
        )
        smallest = np.minimum.accumulate(np.where(d > 1e-9, d, math.inf))
        learnt = np.r_[quantum, np.minimum(smallest, quantum)]  # [k]: after k readings
        out = learnt[np.maximum(upto, 0)]
        self._last = float(dist[-1])
        self._learnt_t = float(o.t[i0 + upto[-1] - 1])
        self.value = float(learnt[-1]) if math.isfinite(learnt[-1]) else self.value
        return np.maximum(np.where(np.isfinite(out), out, 0.0), FLOOR_M)


def _increments(x0: float, x: Array) -> Array:
    """x[i] - x[i - 1] for every i, with x[-1] = x0 (np.diff with prepend, without its
    overhead on the short per-epoch arrays)."""
    before = np.empty_like(x)
    before[0] = x0
    before[1:] = x[:-1]
    return x - before
