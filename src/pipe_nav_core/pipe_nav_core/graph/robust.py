"""Robust losses for the batch smoother's factors, applied by iteratively reweighted least
squares: a factor whose whitened residual norm is e (dimensionless, sqrt(r^T R^-1 r)) enters
the next linear solve with its noise covariance divided by the weight w(e)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# threshold of the Huber loss on the whitened norm of a factor: a 3-row marker fix that is
# right has a norm of about sqrt(3), under 3 in 99 % of cases (chi-square, 3 dof: 11.3 = 3.4^2)
HUBER_K = 3.0


def huber_weight(e: Array | float, k: float = HUBER_K) -> Array:
    """IRLS weight of the Huber loss: 1 for e <= k, k / e beyond (quadratic near zero, linear in
    the tails, so a wrong marker pulls with a bounded force)."""
    e = np.abs(np.asarray(e, dtype=np.float64))
    return np.where(e <= k, 1.0, k / np.maximum(e, 1e-300))


def cauchy_weight(e: Array | float, k: float = HUBER_K) -> Array:
    """IRLS weight of the Cauchy loss, 1 / (1 + (e / k)^2): redescending, a gross outlier ends
    with almost no weight (needs a good start: it is not convex)."""
    e = np.asarray(e, dtype=np.float64)
    return 1.0 / (1.0 + (e / k) ** 2)


def huber_cost(e: Array | float, k: float = HUBER_K) -> Array:
    """The Huber loss rho(e) in the units of e^2 (e^2 for e <= k, 2 k e - k^2 beyond)."""
    e = np.abs(np.asarray(e, dtype=np.float64))
    return np.where(e <= k, e**2, 2.0 * k * e - k**2)
