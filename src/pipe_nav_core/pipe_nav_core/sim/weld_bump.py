"""The jolt of the odometer wheel crossing a girth weld's bead.

The weld bead stands a millimetre or two proud of the bore. When the wheel rolls over it the
pig's body is lifted along its own ``+z`` (base_link: the wheel runs at ``-z``) by a short bump
``z(t) = height exp(-0.5 ((t - t_w) / duration)^2)`` and set down again: a vertical specific
force ``z''(t)`` (zero net velocity and displacement change, so the trajectory's truth is
unchanged to well under a millimetre). The IMU reports interval means, and the mean of ``z''``
over ``(t[i-1], t[i]]`` is exactly ``(z'(t[i]) - z'(t[i-1])) / dt``, so no sub-sampling is
needed. The wheel's extra path over a bead (well under a millimetre per weld) is left out: it
is below the odometer's tick.

Off unless the scenario sets ``weld_bump_height`` > 0 (m of body lift; 0.5 mm over 10 ms gives
a 5 m/s^2 peak).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def weld_passage_times(
    welds: FloatArray, truth_t: FloatArray, truth_s: FloatArray, wheel_x: float = 0.0
) -> FloatArray:
    """Times (s) at which the wheel (``wheel_x`` m ahead of the centreline point along the
    pipe) reaches the weld chainages ``welds`` (m), from the true chainage ``truth_s`` (m,
    non-decreasing) at ``truth_t`` (s). Welds the pig never reaches are left out."""
    s = np.maximum.accumulate(np.asarray(truth_s, dtype=np.float64))
    w = np.asarray(welds, dtype=np.float64) - float(wheel_x)
    w = w[(w > s[0]) & (w < s[-1])] if len(s) else w[:0]
    return np.interp(w, s, np.asarray(truth_t, dtype=np.float64))


def weld_bump_accel(
    t: FloatArray, t_welds: FloatArray, height: float, duration: float
) -> FloatArray:
    """Vertical specific force (N,) m/s^2 along base_link z: the interval mean over
    (t[i-1], t[i]] of z'' for a Gaussian lift of ``height`` m and ``duration`` s (one sigma)
    centred on each of ``t_welds`` (s). The first sample (no interval before it) gets 0."""
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros(len(t))
    if len(t) < 2 or height <= 0.0 or duration <= 0.0 or len(t_welds) == 0:
        return out
    tau = float(duration)
    dt = float(np.median(np.diff(t)))
    reach = int(np.ceil(6.0 * tau / dt)) + 2
    for tw in np.asarray(t_welds, dtype=np.float64):
        k = int(np.searchsorted(t, tw))
        a, b = max(1, k - reach), min(len(t), k + reach + 1)
        if a >= b:
            continue
        x = (t[a - 1 : b] - tw) / tau
        dz = -height / tau * x * np.exp(-0.5 * x * x)  # z'(t), m/s
        out[a:b] += np.diff(dz) / np.diff(t[a - 1 : b])
    return out


__all__ = ["weld_bump_accel", "weld_passage_times"]
