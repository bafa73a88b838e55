"""The batch smoothing problem as a factor graph, linearized about a trajectory.

Variables: the error state delta_k (layout of :mod:`pipe_nav_core.model.state`, ENU navigation
frame, SI units, rad) of every filter epoch k = 0 .. K-1 relative to the linearization point X_k:
truth_k = X_k (+) delta_k.

Factors (each a whitened least-squares term):
- :class:`Prior` on delta_0: the static alignment's (mean x0, covariance P0);
- one between-factor per epoch k >= 1 (:class:`LinearChain` arrays): the error-state dynamics
  delta_k = Phi_k delta_{k-1} + offset_k + w_k, w_k ~ N(0, Qd_k), where offset_k is the
  mechanization from X_{k-1} minus X_k (zero on a trajectory that follows its own IMU);
- :class:`MeasurementFactor` s on one epoch each: residual r = z - h(X_k), Jacobian H
  (r ~= H delta_k + v) and noise R from the filter's own measurement kernels
  (:mod:`pipe_nav_core.model.measurements`), optionally with a robust loss.

The problem holds no solver (:mod:`.solver`) and no knowledge of where its factors came from
(:mod:`.linearize` builds them from the filter's epoch).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Index = NDArray[np.int64]
# variances below this fraction of a covariance's largest are raised to it (whitener): such a
# factor is a constraint, exact to double precision
EIG_FLOOR = 1e-15
MIN_VARIANCE = 1e-24  # and never below this (a marker surveyed exactly, passed at rest)
# evaluates a measurement model at a flat state (SV_SIZE,) and layout index: (r, H, R)
Model = Callable[[Array, Index], tuple[Array, Array, Array]]


def whitener(C: Array) -> Array:
    """W (m, m) with W C W^T = I for a covariance C (m, m): the inverse of its lower Cholesky
    factor. A variance that is exactly zero (the odometer reading error carried from one
    epoch to the next, a marker surveyed exactly) is raised to EIG_FLOOR times the largest
    (at least MIN_VARIANCE), which makes its factor a constraint exact to double precision;
    if C is still not positive definite, its eigenvalues are floored likewise. numpy's LAPACK
    calls only: scipy.linalg's run OpenBLAS threads that cost milliseconds per call on these
    small matrices under load."""
    d = np.diag(C)
    floor = max(EIG_FLOOR * float(d.max()), MIN_VARIANCE)
    if len(d) == 1 or not np.any(C - np.diag(d)):  # diagonal (most measurement noises)
        return np.diag(1.0 / np.sqrt(np.maximum(d, floor)))
    C = 0.5 * (C + C.T)
    zero = np.flatnonzero(d <= floor)
    if len(zero):
        C = C.copy()
        C[zero, zero] = floor
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        s, U = np.linalg.eigh(C)
        s = np.maximum(s, max(EIG_FLOOR * float(s.max()), MIN_VARIANCE))
        return (U / np.sqrt(s)).T
    # inverse of the upper triangular L^T: its LU needs no row exchange (an exact
    # back-substitution), unlike that of L
    return np.linalg.inv(L.T).T


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
        """sqrt(r^T R^-1 r) at the linearization point (dimensionless; R floored as by
        :func:`whitener`)."""
        return float(np.linalg.norm(whitener(self.R) @ self.r))

    @property
    def exact(self) -> bool:
        """Some direction of the measurement has no noise (a marker surveyed exactly: only
        its passage-time error along the track): a constraint, which no robust loss or gate
        can weigh (its whitened residual is round-off over MIN_VARIANCE)."""
        d = np.diag(self.R)
        if len(d) == 1 or not np.any(self.R - np.diag(d)):  # diagonal: its own eigenvalues
            s = np.sort(d)
        else:
            s = np.linalg.eigvalsh(0.5 * (self.R + self.R.T))
        return bool(s[0] <= max(1e-12 * s[-1], MIN_VARIANCE))


@dataclass
class Factors:
    """Measurement factors as arrays, F of them with at most M rows each (rows and columns
    beyond a factor's own m are not read): kind (F,) the filter's update kind (as
    MeasurementFactor.kind), epoch (F,) k, m (F,) rows, r (F, M), H (F, M, n), R (F, M, M)
    (as MeasurementFactor's), robust (F,) the factor takes the robust loss, name (F,) e.g.
    the marker's name. What the batch solver reads of the factors (:func:`.solver.whiten`):
    the compiled linearization writes them so (:mod:`.linearize`), without a model each."""

    kind: NDArray[np.str_]
    epoch: Index
    m: Index
    r: Array
    H: Array
    R: Array
    robust: NDArray[np.bool_]
    name: NDArray[np.str_]

    def __len__(self) -> int:
        return len(self.epoch)

    @classmethod
    def of(cls, factors: Sequence[MeasurementFactor], n: int) -> Factors:
        """The arrays of a list of factors on n error states (in its order)."""
        F = len(factors)
        m = np.array([len(f.r) for f in factors], dtype=np.int64)
        M = int(m.max()) if F else 1
        r, H, R = np.zeros((F, M)), np.zeros((F, M, n)), np.zeros((F, M, M))
        for i, f in enumerate(factors):
            r[i, : m[i]], H[i, : m[i]], R[i, : m[i], : m[i]] = f.r, f.H, f.R
        return cls(
            np.array([f.kind for f in factors], dtype=np.str_),
            np.array([f.epoch for f in factors], dtype=np.int64),
            m, r, H, R,
            np.array([f.robust for f in factors], dtype=bool),
            np.array([f.name for f in factors], dtype=np.str_),
        )  # fmt: skip

    @classmethod
    def join(cls, parts: Sequence[Factors], n: int) -> Factors:
        """The factors of parts, one after the other (rows padded to the widest)."""
        if not parts:
            return cls.of([], n)
        M = max(p.r.shape[1] for p in parts)

        def widened(a: Array, axes: tuple[int, ...]) -> Array:
            """a with zeros appended along axes up to M."""
            pad = [(0, M - a.shape[i] if i in axes else 0) for i in range(a.ndim)]
            return np.pad(a, pad) if any(w for _, w in pad) else a

        return cls(
            np.concatenate([p.kind for p in parts]),
            np.concatenate([p.epoch for p in parts]),
            np.concatenate([p.m for p in parts]),
            np.concatenate([widened(p.r, (1,)) for p in parts]),
            np.concatenate([widened(p.H, (1,)) for p in parts]),
            np.concatenate([widened(p.R, (1, 2)) for p in parts]),
            np.concatenate([p.robust for p in parts]),
            np.concatenate([p.name for p in parts]),
        )


@dataclass
class LinearChain:
    """The whole batch problem linearized about one trajectory (see the module docstring).

    prior: on delta_0; the between-factor from epoch k-1 to k in row k (row 0 unused), stored
    compactly: the rows phi_rows of Phi_k (phi (K, r, n); the other rows are the identity's),
    the rows qd_rows of Qd_k (qd (K, q, n); by symmetry also those columns) and its diagonal
    (qd_diag (K, n); Qd_k is zero elsewhere), the offset (K, n); factors: every measurement
    factor, any order. :meth:`dense` builds one from full matrices.
    """

    prior: Prior
    phi: Array
    qd: Array
    qd_diag: Array
    offset: Array
    phi_rows: Index
    qd_rows: Index
    factors: list[MeasurementFactor] = field(default_factory=list)

    @classmethod
    def dense(
        cls,
        prior: Prior,
        phi: Array,
        qd: Array,
        offset: Array,
        factors: list[MeasurementFactor] | None = None,
    ) -> LinearChain:
        """A chain from full transitions phi (K, n, n) and process noises qd (K, n, n)."""
        n = phi.shape[1]
        every = np.arange(n)
        diag = np.diagonal(qd, axis1=1, axis2=2).copy()
        return cls(prior, phi, qd, diag, offset, every, every, list(factors or []))

    @property
    def K(self) -> int:
        """Number of epochs (variables)."""
        return int(self.offset.shape[0])

    @property
    def n(self) -> int:
        """Error-state size."""
        return int(self.offset.shape[1])

    def transitions(self, a: int, b: int) -> Array:
        """Phi_k (b - a, n, n) of the epochs a .. b-1."""
        out = np.tile(np.eye(self.n), (b - a, 1, 1))
        out[:, self.phi_rows] = self.phi[a:b]
        return out

    def process_noise(self, a: int, b: int) -> Array:
        """Qd_k (b - a, n, n) of the epochs a .. b-1."""
        n = self.n
        out = np.zeros((b - a, n, n))
        i = np.arange(n)
        out[:, i, i] = self.qd_diag[a:b]
        out[:, self.qd_rows] = self.qd[a:b]
        out[:, :, self.qd_rows] = np.swapaxes(self.qd[a:b], 1, 2)
        return out

    def by_epoch(self) -> list[list[int]]:
        """Indices into factors, grouped by epoch (K lists)."""
        out: list[list[int]] = [[] for _ in range(self.K)]
        for i, f in enumerate(self.factors):
            out[f.epoch].append(i)
        return out
