"""Smooth piecewise profiles with closed-form integrals and derivatives.

Everything the simulator moves (speed along the pipe, roll rate of the pig, curvature of the pipe
along its chainage) is built from *levels joined by smooth transitions*. A transition uses the
quintic smootherstep ``S(x) = 6x^5 - 15x^4 + 10x^3`` on ``x in [0, 1]``, whose first and second
derivatives vanish at both ends, so a profile is C2 and its integral C3. That keeps the IMU signal
(which contains the derivative of the speed) continuous, and the interval means well defined.

The independent variable is generic (time in s, or chainage in m); units follow the caller.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def smoothstep(x: ArrayLike) -> FloatArray:
    """Quintic smootherstep S(x), clamped: 0 for x <= 0, 1 for x >= 1 (dimensionless)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def smoothstep_deriv(x: ArrayLike) -> FloatArray:
    """dS/dx, zero outside (0, 1) (dimensionless)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return 30.0 * x * x * (x - 1.0) ** 2


def smoothstep_integral(x: ArrayLike) -> FloatArray:
    """Integral of S from 0 to x: 0 for x <= 0, x^6 - 3x^5 + 2.5x^4 inside, 0.5 + (x - 1) beyond."""
    x = np.asarray(x, dtype=np.float64)
    c = np.clip(x, 0.0, 1.0)
    inside = c**4 * (c * (c - 3.0) + 2.5)
    return inside + np.maximum(x - 1.0, 0.0)


class RampProfile:
    """A function f(u) made of constant levels joined by non-overlapping smooth transitions.

    Transition j starts at ``starts[j]``, lasts ``durations[j]`` and goes from ``levels[j]`` to
    ``levels[j + 1]``; before the first transition f = levels[0]. The profile provides f, df/du and
    the integral F(u) = F0 + integral of f from u0 to u, all exact and vectorized. Units: u in s or
    m, f in whatever the caller uses (m/s for speed, rad/s for roll rate, 1/m for curvature).
    """

    def __init__(
        self,
        starts: Sequence[float] | FloatArray,
        durations: Sequence[float] | FloatArray,
        levels: Sequence[float] | FloatArray,
        u0: float = 0.0,
        f0_integral: float = 0.0,
    ) -> None:
        a = np.asarray(starts, dtype=np.float64).reshape(-1)
        d = np.asarray(durations, dtype=np.float64).reshape(-1)
        lv = np.asarray(levels, dtype=np.float64).reshape(-1)
        if len(lv) != len(a) + 1 or len(d) != len(a):
            raise ValueError("RampProfile needs len(levels) == len(starts) + 1 == len(durations)+1")
        if np.any(d <= 0.0):
            raise ValueError("RampProfile transition durations must be positive")
        if len(a) > 1 and np.any(a[1:] < a[:-1] + d[:-1] - 1e-9 * np.maximum(1.0, np.abs(a[1:]))):
            raise ValueError("RampProfile transitions must not overlap")
        if len(a) and a[0] < u0:
            raise ValueError("RampProfile transitions must start at or after u0")
        self.starts = a
        self.durations = d
        self.levels = lv
        self.u0 = float(u0)
        self.f0_integral = float(f0_integral)
        dl = np.diff(lv)
        self._dl = dl
        # Integral at the start of each transition.
        fa = np.empty(len(a))
        if len(a):
            fa[0] = f0_integral + lv[0] * (a[0] - u0)
            if len(a) > 1:
                gap = a[1:] - a[:-1]
                inc = lv[:-2] * gap + dl[:-1] * (0.5 * d[:-1] + gap - d[:-1])
                fa[1:] = fa[0] + np.cumsum(inc)
        self._fa = fa

    @property
    def end(self) -> float:
        """Where the last transition ends (u0 if there is none)."""
        if len(self.starts) == 0:
            return self.u0
        return float(self.starts[-1] + self.durations[-1])

    def _locate(self, u: FloatArray) -> tuple[FloatArray, FloatArray]:
        j = np.searchsorted(self.starts, u, side="right") - 1
        return j, np.maximum(j, 0)

    def value(self, u: ArrayLike) -> FloatArray:
        """f(u)."""
        u = np.asarray(u, dtype=np.float64)
        if len(self.starts) == 0:
            return np.full(u.shape, self.levels[0])
        j, jc = self._locate(u)
        x = (u - self.starts[jc]) / self.durations[jc]
        out = self.levels[jc] + self._dl[jc] * smoothstep(x)
        return np.where(j < 0, self.levels[0], out)

    def deriv(self, u: ArrayLike) -> FloatArray:
        """df/du (zero on the levels)."""
        u = np.asarray(u, dtype=np.float64)
        if len(self.starts) == 0:
            return np.zeros(u.shape)
        j, jc = self._locate(u)
        x = (u - self.starts[jc]) / self.durations[jc]
        out = self._dl[jc] * smoothstep_deriv(x) / self.durations[jc]
        return np.where(j < 0, 0.0, out)

    def integral(self, u: ArrayLike) -> FloatArray:
        """F(u) = f0_integral + integral of f from u0 to u."""
        u = np.asarray(u, dtype=np.float64)
        if len(self.starts) == 0:
            return self.f0_integral + self.levels[0] * (u - self.u0)
        j, jc = self._locate(u)
        du = u - self.starts[jc]
        x = du / self.durations[jc]
        out = (
            self._fa[jc]
            + self.levels[jc] * du
            + self._dl[jc] * self.durations[jc] * smoothstep_integral(x)
        )
        before = self.f0_integral + self.levels[0] * (u - self.u0)
        return np.where(j < 0, before, out)

    def invert_integral(
        self, target: ArrayLike, lo: float, hi: float, iterations: int = 100
    ) -> FloatArray:
        """Smallest u in [lo, hi] with F(u) >= target, by vectorized bisection (F non-decreasing).

        Accurate to about 1e-12 of (hi - lo); requires f >= 0 on [lo, hi].
        """
        tgt = np.asarray(target, dtype=np.float64)
        a = np.full(tgt.shape, float(lo))
        b = np.full(tgt.shape, float(hi))
        for _ in range(iterations):
            m = 0.5 * (a + b)
            below = self.integral(m) < tgt
            a = np.where(below, m, a)
            b = np.where(below, b, m)
            if np.all(b - a <= 1e-13 * max(1.0, abs(hi))):
                break
        return b
