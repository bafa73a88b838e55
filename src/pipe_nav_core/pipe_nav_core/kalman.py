"""Error-state Kalman filter: covariance propagation and gated updates.

Every update is chi-square gated on its normalized innovation squared (NIS); rejected updates
are counted per measurement type, never silently lost. The measurement contract is
:class:`pipe_nav_core.measurements.Measurement` (residual, Jacobian, noise).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from .measurements import Measurement

Array = NDArray[np.float64]


@lru_cache(maxsize=64)
def chi2_threshold(probability: float, dof: int) -> float:
    """Chi-square quantile: NIS above it is rejected."""
    return float(chi2.ppf(probability, dof))


@dataclass
class UpdateStats:
    """Accepted and rejected counts and the NIS sum, per measurement name."""

    accepted: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    rejected: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    nis_sum: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    dof_sum: dict[str, int] = field(default_factory=lambda: defaultdict(int))

    def as_dict(self) -> dict[str, float | int]:
        out: dict[str, float | int] = {}
        for name in sorted(set(self.accepted) | set(self.rejected)):
            out[f"accepted_{name}"] = self.accepted[name]
            out[f"rejected_{name}"] = self.rejected[name]
            if self.dof_sum[name]:
                out[f"mean_nis_per_dof_{name}"] = self.nis_sum[name] / self.dof_sum[name]
        return out


class ErrorStateKF:
    """Mean x and covariance P of the error state dx = truth (-) linearization point.

    The usual error-state EKF keeps x at zero: the caller injects every correction into its
    nominal state and calls :meth:`reset_mean` (it relinearizes after each update). A filter
    linearized about a fixed reference trajectory (the iterated smoother's passes) keeps x
    instead: its estimate is reference (+) x.
    """

    def __init__(self, P0: Array, gate_probability: float, x0: Array | None = None) -> None:
        self.P = np.array(P0, dtype=np.float64)
        self.x = np.zeros(self.P.shape[0]) if x0 is None else np.array(x0, dtype=np.float64)
        self.gate_probability = gate_probability
        self.stats = UpdateStats()

    def predict(self, phi: Array, qd: Array, offset: Array | None = None) -> None:
        """x <- phi x + offset (offset: the nominal transition's miss of the new linearization
        point, zero when the nominal is propagated itself); P <- phi P phi^T + qd."""
        self.x = phi @ self.x if offset is None else phi @ self.x + offset
        P = phi @ self.P @ phi.T + qd
        self.P = 0.5 * (P + P.T)

    def reset_mean(self) -> None:
        """The caller has injected x into its nominal state."""
        self.x[:] = 0.0

    def update(self, m: Measurement, *, gate: bool = True) -> Array | None:
        """Apply one measurement (residual evaluated at the linearization point); returns the
        correction added to x, or None if rejected by the innovation gate."""
        H, R = m.H, m.R
        r = m.residual - H @ self.x
        PHt = self.P @ H.T
        S = H @ PHt + R
        try:
            S_inv_r = np.linalg.solve(S, r)
        except np.linalg.LinAlgError:
            self.stats.rejected[m.name] += 1
            return None
        nis = float(r @ S_inv_r)
        dof = len(r)
        if not np.isfinite(nis) or (gate and nis > chi2_threshold(self.gate_probability, dof)):
            self.stats.rejected[m.name] += 1
            return None
        K = np.linalg.solve(S, PHt.T).T
        dx = K @ r
        self.x = self.x + dx
        I_KH = np.eye(self.P.shape[0]) - K @ H
        P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        self.P = 0.5 * (P + P.T)
        self.stats.accepted[m.name] += 1
        self.stats.nis_sum[m.name] += nis
        self.stats.dof_sum[m.name] += dof
        return dx
