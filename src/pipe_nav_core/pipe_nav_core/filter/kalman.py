"""Error-state Kalman filter: covariance propagation and gated updates.

Every update is chi-square gated on its normalized innovation squared (NIS); rejected updates
are counted per measurement type, never silently lost. The measurement contract is
:class:`pipe_nav_core.model.measurements.Measurement` (residual, Jacobian, noise).
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
from functools import lru_cache
from statistics import NormalDist
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.jit import kernel

if TYPE_CHECKING:
    from pipe_nav_core.model.measurements import Measurement

Array = NDArray[np.float64]


def _chi2_upper_tail(dof: int, x: float) -> tuple[float, float]:
    """(Q, f): the upper tail P(X > x) and the density at x of a chi-square with an integer
    number of degrees of freedom, in closed form (sums of Poisson terms, with erfc for odd
    dof): accurate to round-off in relative terms far into the tail."""
    h = 0.5 * x
    if dof % 2 == 0:
        term, q = math.exp(-h), 0.0
        for j in range(dof // 2):
            term = math.exp(-h) if j == 0 else term * h / j
            q += term
    else:
        term = math.sqrt(h / math.pi) * math.exp(-h) * 2.0  # h^(1/2) e^-h / Gamma(3/2)
        q = math.erfc(math.sqrt(h))
        for j in range(dof // 2):
            q += term
            term *= h / (j + 1.5)
    density = math.exp((0.5 * dof - 1.0) * math.log(x) - h - 0.5 * dof * math.log(2.0)
                       - math.lgamma(0.5 * dof))  # fmt: skip
    return q, density


@lru_cache(maxsize=64)
def chi2_threshold(probability: float, dof: int) -> float:
    """Chi-square quantile for an integer dof (the gates' m rows): NIS above it is rejected.
    Newton's method on the log of the closed-form upper tail, from the Wilson-Hilferty
    approximation; equal to scipy.stats.chi2.ppf to about 1e-14 (tested), without scipy's
    0.2 s import in every command."""
    tail = 1.0 - probability
    if not (0.0 < tail < 1.0 and dof >= 1):
        raise ValueError(f"chi-square quantile of probability {probability} with {dof} dof")
    z = NormalDist().inv_cdf(probability)
    x = dof * max(1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof)), 0.1) ** 3
    for _ in range(100):
        q, f = _chi2_upper_tail(dof, x)
        step = (math.log(q) - math.log(tail)) * q / f  # Newton on log Q(x) = log tail
        x = max(x + step, 0.5 * x)
        if abs(step) <= 1e-15 * x:
            break
    return x


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
def joseph_in_place(
    P: Array, x: Array, H: Array, R: Array, residual: Array, nis_max: float, dx: Array
) -> tuple[float, bool]:
    """One gated update of (x, P) with m rows (m small), in place: returns (nis, applied).

    r = residual - H x, S = H P H^T + R, NIS = r^T S^-1 r; the update is skipped (x, P and
    dx as they were, applied False) when S is singular (nis = nan) or NIS is not finite or
    above nis_max. Else K = P H^T S^-1, dx = K r, x <- x + dx and the Joseph form
    P <- (I - KH) P (I - KH)^T + K R K^T, each factor (I - KH) applied as a rank-m correction,
    then symmetrized. Loops instead of numpy calls, and P overwritten instead of copied: with
    n ~ 40 and m <= 3 numpy's per-call overhead, and then the allocations and copies of
    (n, n) arrays, were most of an update's time.
    """
    m, n = H.shape
    r = residual.copy()
    for a in range(m):
        for j in range(n):
            r[a] -= H[a, j] * x[j]
    # PHt (n, m) and HP (m, n) (P need not be exactly symmetric)
    PHt = np.zeros((n, m))
    HP = np.zeros((m, n))
    for a in range(m):
        for j in range(n):
            h = H[a, j]
            if h != 0.0:  # H is sparse; skipping its zeros changes no sum
                for i in range(n):
                    PHt[i, a] += P[i, j] * h
                    HP[a, i] += h * P[j, i]
    # solve S [y, K^T] = [r, PHt^T] by Gaussian elimination with partial pivoting
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
            return np.nan, False
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
        return nis, False
    KT = rhs[:, 1:]  # K transposed (m, n): the inner loops below run along its rows
    for i in range(n):
        acc = 0.0
        for a in range(m):
            acc += KT[a, i] * r[a]
        dx[i] = acc
    # P <- B = (I - KH) P, then B (I - KH)^T + K R K^T: HP and PHt hold what is read of P
    for i in range(n):
        for a in range(m):
            k = KT[a, i]
            for j in range(n):
                P[i, j] -= k * HP[a, j]
    BHt = np.zeros((n, m))
    KR = np.zeros((n, m))
    for a in range(m):
        for j in range(n):
            h = H[a, j]
            if h != 0.0:
                for i in range(n):
                    BHt[i, a] += P[i, j] * h
    for i in range(n):
        for a in range(m):
            for b in range(m):
                KR[i, a] += KT[b, i] * R[b, a]
    for i in range(n):
        for a in range(m):
            c1, c2 = KR[i, a], BHt[i, a]
            for j in range(n):
                P[i, j] += c1 * KT[a, j] - c2 * KT[a, j]
    for i in range(n):
        for j in range(i, n):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v
        x[i] += dx[i]
    return nis, True


@kernel
def predict_k(x: Array, P: Array, phi: Array, qd: Array, offset: Array) -> None:
    """In place: x <- phi x + offset; P <- phi P phi^T + qd, symmetrized (P symmetric).

    Only the rows of phi that differ from the identity's (the attitude, velocity and position
    errors, some 11 of 40) are multiplied out: the rest of P is carried over as it is."""
    n = x.shape[0]
    rows = np.empty(n, dtype=np.int64)
    moved = np.zeros(n, dtype=np.bool_)
    nr = 0
    for i in range(n):
        for j in range(n):
            if phi[i, j] != (1.0 if i == j else 0.0):
                rows[nr] = i
                moved[i] = True
                nr += 1
                break
    M = np.zeros((nr, n))  # rows of phi P
    xn = x.copy()
    for a in range(nr):
        i = rows[a]
        acc = 0.0
        for k in range(n):
            f = phi[i, k]
            if f != 0.0:
                acc += f * x[k]
                for j in range(n):
                    M[a, j] += f * P[k, j]
        xn[i] = acc
    Pn = P.copy()
    for a in range(nr):
        i = rows[a]
        for j in range(n):
            if moved[j]:
                acc = 0.0
                for k in range(n):
                    acc += M[a, k] * phi[j, k]
                Pn[i, j] = acc
            else:
                Pn[i, j] = M[a, j]
                Pn[j, i] = M[a, j]
    for i in range(n):
        x[i] = xn[i] + offset[i]
        for j in range(i, n):
            v = 0.5 * ((Pn[i, j] + qd[i, j]) + (Pn[j, i] + qd[j, i]))
            P[i, j] = v
            P[j, i] = v


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
        off = np.zeros(len(self.x)) if offset is None else np.asarray(offset, dtype=np.float64)
        predict_k(self.x, self.P, np.ascontiguousarray(phi), np.ascontiguousarray(qd), off)

    def reset_mean(self) -> None:
        """The caller has injected x into its nominal state."""
        self.x[:] = 0.0

    def update(self, m: Measurement, *, gate: bool = True) -> Array | None:
        """Apply one measurement (residual evaluated at the linearization point); returns the
        correction added to x, or None if rejected by the innovation gate."""
        dof = len(m.residual)
        x = np.array(self.x, dtype=np.float64)  # copies: a caller may hold the old x and P
        P = np.array(self.P, dtype=np.float64)
        dx = np.zeros(len(x))
        nis, applied = joseph_in_place(
            P,
            x,
            np.ascontiguousarray(m.H, dtype=np.float64),
            np.ascontiguousarray(m.R, dtype=np.float64),
            np.ascontiguousarray(m.residual, dtype=np.float64),
            chi2_threshold(self.gate_probability, dof) if gate else np.inf,
            dx,
        )
        if not applied:
            self.stats.rejected[m.name] += 1
            return None
        self.x, self.P = x, P
        self.stats.accepted[m.name] += 1
        self.stats.nis_sum[m.name] += nis
        self.stats.dof_sum[m.name] += dof
        return dx
