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

from .jit import kernel
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


@kernel
def _joseph_update(
    P: Array, x: Array, H: Array, R: Array, residual: Array, nis_max: float
) -> tuple[float, Array, Array, Array]:
    """One gated update of (x, P) with m rows (m small): returns (nis, dx, x_new, P_new).

    r = residual - H x, S = H P H^T + R, NIS = r^T S^-1 r; the update is skipped (dx, x_new,
    P_new empty) when S is singular (nis = nan) or NIS is not finite or above nis_max. Else
    K = P H^T S^-1, x_new = x + K r and the Joseph form P_new = (I - KH) P (I - KH)^T + K R K^T,
    each factor (I - KH) applied as a rank-m correction, then symmetrized. Loops instead of
    numpy calls: with n ~ 40 and m <= 3 the per-call overhead of numpy dominated.
    """
    m, n = H.shape
    empty1, empty2 = np.empty(0), np.empty((0, 0))
    r = residual.copy()
    for a in range(m):
        for j in range(n):
            r[a] -= H[a, j] * x[j]
    # PHt (n, m) and HP (m, n) (P need not be exactly symmetric)
    PHt = np.zeros((n, m))
    HP = np.zeros((m, n))
    for a in range(m):
        for i in range(n):
            acc_ph = 0.0
            acc_hp = 0.0
            for j in range(n):
                acc_ph += P[i, j] * H[a, j]
                acc_hp += H[a, j] * P[j, i]
            PHt[i, a] = acc_ph
            HP[a, i] = acc_hp
    # solve S [y, Z] = [r, PHt^T] by Gaussian elimination with partial pivoting
    S = R.copy()
    for a in range(m):
        for b in range(m):
            for j in range(n):
                S[a, b] += H[a, j] * PHt[j, b]
    rhs = np.empty((m, n + 1))
    for a in range(m):
        rhs[a, 0] = r[a]
        for i in range(n):
            rhs[a, i + 1] = PHt[i, a]
    for k in range(m):
        piv = k
        for i in range(k + 1, m):
            if abs(S[i, k]) > abs(S[piv, k]):
                piv = i
        if S[piv, k] == 0.0:
            return np.nan, empty1, empty1, empty2
        if piv != k:
            for j in range(m):
                S[k, j], S[piv, j] = S[piv, j], S[k, j]
            for j in range(n + 1):
                rhs[k, j], rhs[piv, j] = rhs[piv, j], rhs[k, j]
        for i in range(k + 1, m):
            f = S[i, k] / S[k, k]
            for j in range(k, m):
                S[i, j] -= f * S[k, j]
            for j in range(n + 1):
                rhs[i, j] -= f * rhs[k, j]
    for k in range(m - 1, -1, -1):
        for j in range(n + 1):
            acc = rhs[k, j]
            for i in range(k + 1, m):
                acc -= S[k, i] * rhs[i, j]
            rhs[k, j] = acc / S[k, k]
    nis = 0.0
    for a in range(m):
        nis += r[a] * rhs[a, 0]
    if not np.isfinite(nis) or nis > nis_max:
        return nis, empty1, empty1, empty2
    K = np.empty((n, m))
    for i in range(n):
        for a in range(m):
            K[i, a] = rhs[a, i + 1]
    dx = np.zeros(n)
    for i in range(n):
        for a in range(m):
            dx[i] += K[i, a] * r[a]
    # B = (I - KH) P; P_new = B (I - KH)^T + K R K^T
    B = P.copy()
    for i in range(n):
        for j in range(n):
            for a in range(m):
                B[i, j] -= K[i, a] * HP[a, j]
    BHt = np.zeros((n, m))
    KR = np.zeros((n, m))
    for i in range(n):
        for a in range(m):
            for j in range(n):
                BHt[i, a] += B[i, j] * H[a, j]
            for b in range(m):
                KR[i, a] += K[i, b] * R[b, a]
    for i in range(n):
        for j in range(n):
            for a in range(m):
                B[i, j] += KR[i, a] * K[j, a] - BHt[i, a] * K[j, a]
    P_new = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            P_new[i, j] = 0.5 * (B[i, j] + B[j, i])
    return nis, dx, x + dx, P_new


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
        dof = len(m.residual)
        nis, dx, x, P = _joseph_update(
            np.ascontiguousarray(self.P, dtype=np.float64),
            np.ascontiguousarray(self.x, dtype=np.float64),
            np.ascontiguousarray(m.H, dtype=np.float64),
            np.ascontiguousarray(m.R, dtype=np.float64),
            np.ascontiguousarray(m.residual, dtype=np.float64),
            chi2_threshold(self.gate_probability, dof) if gate else np.inf,
        )
        if not len(dx):
            self.stats.rejected[m.name] += 1
            return None
        self.x, self.P = x, P
        self.stats.accepted[m.name] += 1
        self.stats.nis_sum[m.name] += nis
        self.stats.dof_sum[m.name] += dof
        return dx
