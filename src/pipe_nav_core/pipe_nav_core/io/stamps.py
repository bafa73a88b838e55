"""Exact conversions between float seconds and integer nanoseconds (ROS time stamps).

A ROS ``builtin_interfaces/Time`` is (sec: int32, nanosec: uint32 in [0, 1e9)); negative times
have a negative ``sec`` and a positive ``nanosec`` (-1.7 s = (-2, 3e8)). Seconds as float64
resolve a nanosecond only below about 2**22 s (48 days); epoch stamps (1.7e9 s) keep about
0.24 microseconds, which is ample for navigation.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

NS_PER_S = 1_000_000_000


def sec_to_ns(t: ArrayLike) -> NDArray[np.int64]:
    """Seconds (float) -> integer nanoseconds, rounded to the nearest ns, vectorized.

    The integer part and the fraction are converted separately so that no precision is lost
    to the product ``t * 1e9`` (exact for every float64 that holds whole nanoseconds).
    """
    t = np.asarray(t, dtype=np.float64)
    whole = np.floor(t)
    frac_ns = np.rint((t - whole) * 1e9).astype(np.int64)
    return whole.astype(np.int64) * NS_PER_S + frac_ns


_EXACT_NS = 2**53  # integers below this are exact in float64


def ns_to_sec(ns: ArrayLike) -> NDArray[np.float64]:
    """Integer nanoseconds -> float seconds, vectorized.

    Below 2**53 ns (104 days) this is the correctly rounded ns / 1e9, so that times written from
    floats (e.g. ``i / 200.0``) read back bit-identical; above, sec + nanosec / 1e9 (epoch
    stamps, about 0.1 microsecond rounding).
    """
    ns = np.asarray(ns, dtype=np.int64)
    small = np.abs(ns) < _EXACT_NS
    sec = np.floor_divide(ns, NS_PER_S)
    nsec = ns - sec * NS_PER_S
    big = sec.astype(np.float64) + nsec.astype(np.float64) / 1e9
    return np.where(small, ns.astype(np.float64) / 1e9, big)


def ns_to_sec_scalar(ns: int) -> float:
    """Integer nanoseconds -> float seconds for one value (same rule as :func:`ns_to_sec`)."""
    ns = int(ns)
    if abs(ns) < _EXACT_NS:
        return ns / 1e9
    sec, nsec = divmod(ns, NS_PER_S)
    return float(sec) + nsec / 1e9


def split_ns(ns: int) -> tuple[int, int]:
    """Integer nanoseconds -> (sec, nanosec) with 0 <= nanosec < 1e9 (negative-safe)."""
    sec, nsec = divmod(int(ns), NS_PER_S)
    return sec, nsec


def sec_to_ns_scalar(t: float) -> int:
    """Seconds -> integer nanoseconds for one value (same rounding as :func:`sec_to_ns`)."""
    return int(sec_to_ns(np.float64(t)))
