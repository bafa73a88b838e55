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
    """Covariance P of the error state and the update step; the caller applies dx to its state."""

    def __init__(self, P0: Array, gate_probability: float) -> None:
        self.P = np.array(P0, dtype=np.float64)
        self.gate_probability = gate_probability
        self.stats = UpdateStats()

    def predict(self, phi: Array, qd: Array) -> None:
        P = phi @ self.P @ phi.T + qd
        self.P = 0.5 * (P + P.T)

    def update(self, m: Measurement, *, gate: bool = True) -> Array | None:
        """Apply one measurement; returns the error-state correction dx, or None if rejected."""
        H, r, R = m.H, m.residual, m.R
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
        I_KH = np.eye(self.P.shape[0]) - K @ H
        P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        self.P = 0.5 * (P + P.T)
        self.stats.accepted[m.name] += 1
        self.stats.nis_sum[m.name] += nis
        self.stats.dof_sum[m.name] += dof
        return dx
