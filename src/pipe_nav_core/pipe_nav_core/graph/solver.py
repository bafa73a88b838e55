"""Linear least-squares solve of a :class:`~.problem.LinearChain`: square-root information
elimination in time order (sparse QR of the whole batch, one block of epochs at a time).

The Jacobian of the batch problem is block-bidiagonal (a between-factor couples epochs k-1
and k, every other factor one epoch), so eliminating the variables in time order keeps the
fill-in to one block: each step is a small dense QR of

    [ R~_{k-1}          0      | z~_{k-1} ]   (what is known of delta_{k-1} so far)
    [ -W_k Phi_k        W_k    | W_k o_k  ]   (the between-factor, W_k = Qd_k^{-1/2})
    [ 0                 M_k    | m_k      ]   (the whitened measurements of epoch k)

which leaves the rows of delta_{k-1} (R_kk, R_k,k+1, z_k, kept for back-substitution) and the
information R~_k on delta_k. This is the QR route of GTSAM's elimination, not the normal
equations: the error state holds nearly constant parameters (boresight, scale-factor and
misalignment matrices, whose process noise is 1e-8 to 1e-9 per sqrt(s)), and the normal
equations square their between-factor weights (~1e19) against the measurement information
(~1 to 1e4), which a Cholesky factor of them cannot resolve in double precision.

Marginal covariances come from the same factor, backwards: Sigma_K = R~_K^-1 R~_K^-T and
Sigma_k = R_kk^-1 R_kk^-T + G_k Sigma_{k+1} G_k^T with G_k = R_kk^-1 R_k,k+1.

:class:`Eliminator` takes the epochs one at a time (the Gauss-Newton iterations feed it as
their linearization pass runs, :class:`.batch.StreamingSolve`, and never hold the problem);
:func:`solve_chain` feeds it a whole :class:`~.problem.LinearChain`, whitening (Cholesky factors
of every noise covariance) batched, PIECE epochs or all factors of one size at once. The rows
kept for back-substitution (R_kk, R_k,k+1, z_k: 23 kB per epoch with 38 error states) are
stored like the forward pass's recording, beyond RAM_BUDGET_BYTES in a temporary directory
(:class:`pipe_nav_core.smooth.chunks.Chunks`).

The step's QR calls LAPACK's dgeqrf through scipy.linalg.lapack, without scipy.linalg's front
ends (whose checks cost more than the work on these small matrices), in place on a
Fortran-ordered block. The whiteners (Cholesky factors and their inverses), the triangular
inverses and the back-substitution's recursion run compiled, a piece of epochs per call
(:mod:`.linalg`): a triangular inverse is a third of a general one's work.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.graph.linalg import back_substitute_k, inv_lower_k, whiteners_k
from pipe_nav_core.graph.problem import (
    EIG_FLOOR,
    MIN_VARIANCE,
    Factors,
    LinearChain,
    MeasurementFactor,
    whitener,
)
from pipe_nav_core.smooth.chunks import RAM_BUDGET_BYTES, Chunks

Array = NDArray[np.float64]

PIECE = 512  # epochs whose between-factors are whitened at once (bounds the temporaries)
# epochs per chunk of the rows kept for back-substitution (a multiple of PIECE): 48 MB with 38
# error states (4096 took 96 MB a chunk, and the store holds up to seven: 0.3 GB more at 100 km)
STORE_EPOCHS = 4 * PIECE


@dataclass
class ChainSolution:
    """Result of :func:`solve_chain`: delta (K, n) the least-squares error state of every epoch
    relative to the linearization point; var (K, n) the diagonals of its marginal covariances
    (cov (K, n, n) the covariances themselves when asked for); cost0: the weighted cost at
    delta = 0 (the linearization point), cost: the cost the linear model predicts at delta
    (both sums of squared whitened residuals, dimensionless)."""

    delta: Array
    var: Array
    cost0: float
    cost: float
    cov: Array | None = None


def inv_triangular(T: Array, lower: bool = False) -> Array:
    """Inverses of a stack of triangular matrices T (B, m, m) (upper, or lower with lower),
    each by substitution (:func:`.linalg.inv_lower_k`), which reads only that triangle of T
    (what lies on the other side is ignored); zero on the other side of the inverses."""
    if np.any(np.diagonal(T, axis1=1, axis2=2) == 0.0):
        raise np.linalg.LinAlgError("singular triangular matrix")
    out = np.empty(T.shape)
    # an upper triangular T's inverse is the transpose of that of its (lower) transpose
    inv_lower_k(np.ascontiguousarray(T if lower else np.swapaxes(T, 1, 2)), out)
    return out if lower else np.swapaxes(out, 1, 2)


def whiteners(C: Array) -> Array:
    """:func:`problem.whitener` of a stack of covariances C (B, m, m) at once (B, m, m):
    compiled (:func:`.linalg.whiteners_k`), one by one where one is not positive definite."""
    C = np.ascontiguousarray(C, dtype=np.float64)
    if not len(C):
        return C.copy()
    i = np.arange(C.shape[1])
    floor = np.maximum(EIG_FLOOR * C[:, i, i].max(axis=1), MIN_VARIANCE)
    W = np.empty(C.shape)
    if whiteners_k(C, floor, W):
        return W
    return np.stack([whitener(c) for c in C])


@dataclass
class WhitenedFactors:
    """The measurement factors whitened at once (in epoch order, see :func:`whiten`): rows
    (M, n) = W H and rhs (M,) = W r of every factor, factor i's rows start[i] .. start[i+1]
    (order: the factors sorted by epoch, ``order``); norm (F,) = ||W r|| per factor of the
    chain's list; exact (F,): factors with a noise-free direction (MeasurementFactor.exact)."""

    rows: Array
    rhs: Array
    start: NDArray[np.int64]
    order: NDArray[np.int64]
    epochs: NDArray[np.int64]
    norm: Array
    exact: NDArray[np.bool_]


def whiten(factors: Factors | Sequence[MeasurementFactor], n: int) -> WhitenedFactors:
    """Whiten every factor (:class:`~.problem.Factors`, or a list of them), batched by its
    number of rows."""
    fs = factors if isinstance(factors, Factors) else Factors.of(factors, n)
    F = len(fs)
    order = np.argsort(fs.epoch, kind="stable")
    sizes = fs.m[order]
    start = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    rows = np.zeros((int(start[-1]), n))
    rhs = np.zeros(int(start[-1]))
    norm = np.zeros(F)
    exact = np.zeros(F, dtype=bool)
    for m in np.unique(sizes):
        pos = np.flatnonzero(sizes == m)  # positions in the sorted order
        idx = order[pos]
        R = fs.R[idx, :m, :m]
        H = fs.H[idx, :m]
        r = fs.r[idx, :m]
        W = whiteners(R)
        wr = np.einsum("bij,bj->bi", W, r)
        at = start[pos][:, None] + np.arange(m)[None, :]
        rows[at] = W @ H
        rhs[at] = wr
        norm[idx] = np.linalg.norm(wr, axis=1)
        s = np.linalg.eigvalsh(0.5 * (R + np.swapaxes(R, 1, 2)))
        exact[idx] = s[:, 0] <= np.maximum(1e-12 * s[:, -1], MIN_VARIANCE)
    return WhitenedFactors(rows, rhs, start, order, fs.epoch[order], norm, exact)


def _triangular(A: Array, rows: int) -> Array:
    """The upper triangular factor of A's QR, padded with zero rows to rows x A.shape[1]."""
    R = np.linalg.qr(A, mode="r")
    if R.shape[0] < rows:
        R = np.vstack([R, np.zeros((rows - R.shape[0], R.shape[1]))])
    return R[:rows]


class Eliminator:
    """The elimination of the module docstring fed one epoch at a time, in order: the prior and
    epoch 0's measurements (:meth:`first`), then each epoch's between-factor and
    measurements (:meth:`add`, or :meth:`add_whitened`); :meth:`finish` back-substitutes.
    Measurement rows come whitened (rows (m, n) = W H, rhs (m,) = W r, robust weights already
    applied). Holds one block of information and the rows kept for back-substitution
    (spilled to disk beyond RAM_BUDGET_BYTES), whatever the length of the run."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.K = 0  # epochs added
        self.cost0 = 0.0
        self.cost = 0.0
        self._store = Chunks(2 * n * n + n, RAM_BUDGET_BYTES, STORE_EPOCHS)  # R_kk, R_k,k+1, z_k
        self._out = np.empty((PIECE, 2 * n * n + n))
        self._filled = 0
        self._Rt = np.zeros((n, n))
        self._zt = np.zeros(n)
        self._upper = np.triu(np.ones((n, n)))  # 1 on and above the diagonal, 0 below

    def first(self, x0: Array, P0: Array, rows: Array, rhs: Array) -> None:
        """Epoch 0: the prior (mean x0 (n,), covariance P0 (n, n)) and its measurement rows."""
        n = self.n
        W0 = whitener(P0)
        A = np.vstack([np.c_[W0, W0 @ x0], np.c_[rows, rhs]])
        self.cost0 += float(np.sum(A[:, -1] ** 2))
        T = _triangular(A, n + 1)
        self._Rt, self._zt = T[:n, :n], T[:n, n]
        self.cost += float(T[n, n] ** 2)
        self.K = 1

    def add(self, phi: Array, qd: Array, offset: Array, rows: Array, rhs: Array) -> None:
        """The next epoch: transition phi (n, n), process noise qd (n, n) and offset (n,) of
        its between-factor, and its whitened measurement rows."""
        W = whitener(qd)
        self.add_whitened(W @ phi, W, W @ offset, rows, rhs)

    def add_whitened(self, WPhi: Array, W: Array, Wo: Array, rows: Array, rhs: Array) -> None:
        """:meth:`add` with the between-factor whitened: W Phi, W = Qd^(-1/2), W offset."""
        from scipy.linalg.lapack import dgeqrf

        n = self.n
        nn = n * n
        m = 2 * n + len(rhs)
        # Fortran order: LAPACK's QR (dgeqrf) works on it in place, without a copy
        A = np.zeros((m, 2 * n + 1), order="F")
        A[:n, :n], A[:n, -1] = self._Rt, self._zt
        A[n : 2 * n, :n] = -WPhi
        A[n : 2 * n, n : 2 * n] = W
        A[n : 2 * n, -1] = Wo
        A[2 * n :, n : 2 * n] = rows
        A[2 * n :, -1] = rhs
        self.cost0 += float(Wo @ Wo + rhs @ rhs)
        # the upper triangle of T is R of A = Q R (below it: Householder vectors, not read;
        # R_kk is kept with them, Eliminator._back_substitute reads its upper triangle)
        T, _tau, _work, info = dgeqrf(A, overwrite_a=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"QR failed (dgeqrf info {info})")
        out = self._out[self._filled]
        out[:nn] = T[:n, :n].reshape(nn)
        out[nn : 2 * nn] = T[:n, n : 2 * n].reshape(nn)
        out[2 * nn :] = T[:n, -1]
        self._filled += 1
        if self._filled == PIECE:
            self._flush()
        # (its upper triangle: a product with a mask is one ufunc call, np.triu several)
        self._Rt, self._zt = T[n : 2 * n, n : 2 * n] * self._upper, T[n : 2 * n, -1].copy()
        if m > 2 * n:  # else no row is left over: the linear model fits exactly
            self.cost += float(T[2 * n, -1] ** 2)
        self.K += 1

    def _flush(self) -> None:
        for p, q, view in self._store.claim(self._filled):
            view[:] = self._out[p:q]
        self._filled = 0

    def close(self) -> None:
        """Free the kept rows (and their files) without solving."""
        self._store.close()

    def finish(self, full: bool = False) -> ChainSolution:
        """Back-substitution and marginal covariances (full: also the (K, n, n) covariances);
        frees the kept rows."""
        try:
            self._flush()
            return self._back_substitute(full)
        finally:
            self._store.close()

    def _back_substitute(self, full: bool) -> ChainSolution:
        K, n = self.K, self.n
        nn = n * n
        store = self._store
        delta = np.empty((K, n))
        var = np.empty((K, n))
        full_cov = np.empty((K if full else 0, n, n))
        Ri = np.linalg.inv(self._Rt)  # upper triangular: back-substitution
        delta[-1] = Ri @ self._zt
        S = np.ascontiguousarray(Ri @ Ri.T)  # the marginal covariance, from the last epoch back
        var[-1] = np.diag(S)
        if full:
            full_cov[-1] = S
        for c in range(store.n_chunks - 1, -1, -1):
            block = store.chunk(c)
            for a in range(((len(block) - 1) // PIECE) * PIECE, -1, -PIECE):
                piece = block[a : a + PIECE]
                B = len(piece)
                # per epoch at once: R_kk^-1 (upper triangular: back-substitution), G_k, the
                # solution given delta_{k+1} = 0 and R_kk^-1 R_kk^-T
                Ri = inv_triangular(piece[:, :nn].reshape(B, n, n))
                G = Ri @ piece[:, nn : 2 * nn].reshape(B, n, n)
                d0 = np.einsum("bij,bj->bi", Ri, piece[:, 2 * nn :])
                RRt = Ri @ np.swapaxes(Ri, 1, 2)
                k0 = c * store.chunk_rows + a  # row j holds epoch k0 + j's (from step k0 + j + 1)
                back_substitute_k(G, d0, RRt, S, delta, var, full_cov, k0)
        return ChainSolution(delta, var, self.cost0, self.cost, full_cov if full else None)


def solve_chain(
    chain: LinearChain,
    weights: Array | None = None,
    *,
    full: bool = False,
    whitened: WhitenedFactors | None = None,
) -> ChainSolution:
    """Minimise the chain's weighted least-squares cost over every epoch's error state at once
    (see the module docstring). weights (F,): one per factor of chain.factors, dividing its
    noise covariance (IRLS weights of a robust loss; 0 leaves the factor out; default all 1);
    whitened: :func:`whiten` of the chain's factors, if already made. full: also return the
    marginal covariances (K, n, n)."""
    K, n = chain.K, chain.n
    wf = whitened if whitened is not None else whiten(chain.factors, n)
    w = np.ones(len(chain.factors)) if weights is None else np.asarray(weights, dtype=np.float64)
    # a weight w divides the noise covariance: it scales the whitened rows by sqrt(w)
    scale = np.repeat(np.sqrt(np.maximum(w[wf.order], 0.0)), np.diff(wf.start))
    rows, rhs = wf.rows * scale[:, None], wf.rhs * scale
    first = np.searchsorted(wf.epochs, np.arange(K + 1), side="left")
    at = wf.start[first]  # rows of epoch k: at[k] .. at[k + 1]
    elim = Eliminator(n)
    try:
        elim.first(chain.prior.x0, chain.prior.P0, rows[at[0] : at[1]], rhs[at[0] : at[1]])
        for a in range(1, K, PIECE):
            b = min(a + PIECE, K)
            W = whiteners(chain.process_noise(a, b))
            WPhi = W @ chain.transitions(a, b)
            Wo = np.einsum("bij,bj->bi", W, chain.offset[a:b])
            for j, k in enumerate(range(a, b)):
                s = slice(at[k], at[k + 1])
                elim.add_whitened(WPhi[j], W[j], Wo[j], rows[s], rhs[s])
    except BaseException:
        elim.close()
        raise
    return elim.finish(full)
