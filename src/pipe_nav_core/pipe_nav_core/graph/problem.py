"""The batch smoothing problem as a factor graph, linearized about a trajectory.

Variables: the error state delta_k (layout of :mod:`pipe_nav_core.state`, ENU navigation frame,
SI units, rad) of every filter epoch k = 0 .. K-1 relative to the linearization point X_k:
truth_k = X_k (+) delta_k.

Factors (each a whitened least-squares term):
- :class:`Prior` on delta_0: the static alignment's (mean x0, covariance P0);
- one between-factor per epoch k >= 1 (:class:`LinearChain` arrays): the error-state dynamics
  delta_k = Phi_k delta_{k-1} + offset_k + w_k, w_k ~ N(0, Qd_k), where offset_k is the
  mechanization from X_{k-1} minus X_k (zero on a trajectory that follows its own IMU);
- :class:`MeasurementFactor` s on one epoch each: residual r = z - h(X_k), Jacobian H
  (r ~= H delta_k + v) and noise R from the filter's own measurement kernels
  (:mod:`pipe_nav_core.measurements`), optionally with a robust loss.

The problem holds no solver (:mod:`.solver`) and no knowledge of where its factors came from
(:mod:`.linearize` builds them from the filter's epoch).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Index = NDArray[np.int64]
# evaluates a measurement model at a flat state (SV_SIZE,) and layout index: (r, H, R)
Model = Callable[[Array, Index], tuple[Array, Array, Array]]


@dataclass
class Prior:
    """Gaussian prior on delta_0: mean x0 (n,), covariance P0 (n, n), error-state units."""

    x0: Array
    P0: Array


@dataclass
class MeasurementFactor:
    """One measurement on the error state of one epoch.

    kind: the filter's update kind (epoch.KINDS: nhc, odometer, zupt, zaru, tilt, mag, marker);
    epoch: k; r (m,), H (m, n), R (m, m): the model evaluated at the linearization point;
    model: the same model as a function of any flat state (for relinearization checks and
    tests); robust: the factor takes the robust loss (markers); name: e.g. the marker's name.
    """

    kind: str
    epoch: int
    r: Array
    H: Array
    R: Array
    model: Model
    robust: bool = False
    name: str = ""

    def whitened_norm(self) -> float:
        """sqrt(r^T R^-1 r) at the linearization point (dimensionless)."""
        return float(np.sqrt(self.r @ np.linalg.solve(self.R, self.r)))


@dataclass
class LinearChain:
    """The whole batch problem linearized about one trajectory (see the module docstring).

    prior: on delta_0; phi (K, n, n), qd (K, n, n), offset (K, n): the between-factor from
    epoch k-1 to k in row k (row 0 unused); factors: every measurement factor, any order.
    """

    prior: Prior
    phi: Array
    qd: Array
    offset: Array
    factors: list[MeasurementFactor] = field(default_factory=list)

    @property
    def K(self) -> int:
        """Number of epochs (variables)."""
        return int(self.phi.shape[0])

    @property
    def n(self) -> int:
        """Error-state size."""
        return int(self.phi.shape[1])

    def by_epoch(self) -> list[list[int]]:
        """Indices into factors, grouped by epoch (K lists)."""
        out: list[list[int]] = [[] for _ in range(self.K)]
        for i, f in enumerate(self.factors):
            out[f.epoch].append(i)
        return out
