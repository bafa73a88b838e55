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

The whitening (Cholesky factors of every noise covariance) runs batched, PIECE epochs or all
factors of one size at once; only the elimination is a loop over the epochs. Its rows
(R_kk, R_k,k+1, z_k: 23 kB per epoch with 38 error states) are kept like the forward pass's
recording, beyond RAM_BUDGET_BYTES in a temporary directory (:class:`recording._Chunks`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..recording import CHUNK_EPOCHS, RAM_BUDGET_BYTES, _Chunks
from .problem import EIG_FLOOR, MIN_VARIANCE, LinearChain, MeasurementFactor, whitener

Array = NDArray[np.float64]

PIECE = 512  # epochs whose between-factors are whitened at once (bounds the temporaries)


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


def whiteners(C: Array) -> Array:
    """:func:`problem.whitener` of a stack of covariances C (B, m, m) at once (B, m, m)."""
    C = 0.5 * (C + np.swapaxes(C, 1, 2))
    if not len(C):
        return C.copy()
    m = C.shape[1]
    i = np.arange(m)
    d = C[:, i, i]
    floor = np.maximum(EIG_FLOOR * d.max(axis=1), MIN_VARIANCE)
    low = d <= floor[:, None]
    if low.any():
        C = C.copy()
        b, j = np.nonzero(low)
        C[b, j, j] = floor[b]
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:  # one of them is not positive definite: one by one
        return np.stack([whitener(c) for c in C])
    # inverses of the upper triangular L^T: LU without row exchanges (back-substitution)
    return np.swapaxes(np.linalg.inv(np.swapaxes(L, 1, 2)), 1, 2)


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


def whiten(factors: Sequence[MeasurementFactor], n: int) -> WhitenedFactors:
    """Whiten every factor, batched by its number of rows."""
    F = len(factors)
    order = np.argsort(np.array([f.epoch for f in factors], dtype=np.int64), kind="stable")
    sizes = np.array([len(factors[i].r) for i in order], dtype=np.int64)
    start = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    rows = np.zeros((int(start[-1]), n))
    rhs = np.zeros(int(start[-1]))
    norm = np.zeros(F)
    exact = np.zeros(F, dtype=bool)
    for m in np.unique(sizes):
        pos = np.flatnonzero(sizes == m)  # positions in the sorted order
        idx = order[pos]
        R = np.stack([factors[i].R for i in idx])
        H = np.stack([factors[i].H for i in idx])
        r = np.stack([factors[i].r for i in idx])
        W = whiteners(R)
        wr = np.einsum("bij,bj->bi", W, r)
        at = start[pos][:, None] + np.arange(m)[None, :]
        rows[at] = W @ H
        rhs[at] = wr
        norm[idx] = np.linalg.norm(wr, axis=1)
        s = np.linalg.eigvalsh(0.5 * (R + np.swapaxes(R, 1, 2)))
        exact[idx] = s[:, 0] <= np.maximum(1e-12 * s[:, -1], MIN_VARIANCE)
    epochs = np.array([factors[i].epoch for i in order], dtype=np.int64)
    return WhitenedFactors(rows, rhs, start, order, epochs, norm, exact)


def _triangular(A: Array, rows: int) -> Array:
    """The upper triangular factor of A's QR, padded with zero rows to rows x A.shape[1]."""
    R = np.linalg.qr(A, mode="r")
    if R.shape[0] < rows:
        R = np.vstack([R, np.zeros((rows - R.shape[0], R.shape[1]))])
    return R[:rows]


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
    store = _Chunks(2 * n * n + n, RAM_BUDGET_BYTES)  # per epoch: R_kk, R_k,k+1, z_k
    try:
        return _eliminate(chain, rows, rhs, at, store, full)
    finally:
        store.close()


def _eliminate(
    chain: LinearChain, rows: Array, rhs: Array, at: Array, store: _Chunks, full: bool
) -> ChainSolution:
    K, n = chain.K, chain.n
    nn = n * n
    # epoch 0: the prior and its measurements
    W0 = whitener(chain.prior.P0)
    M, m = rows[at[0] : at[1]], rhs[at[0] : at[1]]
    A = np.vstack([np.c_[W0, W0 @ chain.prior.x0], np.c_[M, m]])
    cost0 = float(np.sum(A[:, -1] ** 2))
    T = _triangular(A, n + 1)
    Rt, zt = T[:n, :n], T[:n, n]
    cost = float(T[n, n] ** 2)
    for a in range(1, K, PIECE):
        b = min(a + PIECE, K)
        W = whiteners(chain.process_noise(a, b))
        WPhi = W @ chain.transitions(a, b)
        Wo = np.einsum("bij,bj->bi", W, chain.offset[a:b])
        out = np.empty((b - a, 2 * nn + n))
        for j, k in enumerate(range(a, b)):
            M, m = rows[at[k] : at[k + 1]], rhs[at[k] : at[k + 1]]
            A = np.zeros((2 * n + len(m), 2 * n + 1))
            A[:n, :n], A[:n, -1] = Rt, zt
            A[n : 2 * n, :n] = -WPhi[j]
            A[n : 2 * n, n : 2 * n] = W[j]
            A[n : 2 * n, -1] = Wo[j]
            A[2 * n :, n : 2 * n] = M
            A[2 * n :, -1] = m
            cost0 += float(Wo[j] @ Wo[j] + m @ m)
            T = _triangular(A, 2 * n + 1)
            out[j, :nn] = T[:n, :n].reshape(nn)
            out[j, nn : 2 * nn] = T[:n, n : 2 * n].reshape(nn)
            out[j, 2 * nn :] = T[:n, -1]
            Rt, zt = T[n : 2 * n, n : 2 * n], T[n : 2 * n, -1]
            cost += float(T[2 * n, -1] ** 2)
        for p, q, view in store.claim(b - a):
            view[:] = out[p:q]
    # back-substitution and marginal covariances, last epoch first
    delta = np.empty((K, n))
    var = np.empty((K, n))
    cov = np.empty((K, n, n)) if full else None
    Ri = np.linalg.inv(Rt)  # upper triangular: back-substitution
    delta[-1] = Ri @ zt
    S = Ri @ Ri.T
    var[-1] = np.diag(S)
    if cov is not None:
        cov[-1] = S
    for c in range(store.n_chunks - 1, -1, -1):
        block = store.chunk(c)
        for a in range(((len(block) - 1) // PIECE) * PIECE, -1, -PIECE):
            piece = block[a : a + PIECE]
            B = len(piece)
            # per epoch at once: R_kk^-1 (upper triangular: back-substitution), G_k, the
            # solution given delta_{k+1} = 0 and R_kk^-1 R_kk^-T
            Ri = np.linalg.inv(piece[:, :nn].reshape(B, n, n))
            G = Ri @ piece[:, nn : 2 * nn].reshape(B, n, n)
            d0 = np.einsum("bij,bj->bi", Ri, piece[:, 2 * nn :])
            RRt = Ri @ np.swapaxes(Ri, 1, 2)
            for j in range(B - 1, -1, -1):
                k = c * CHUNK_EPOCHS + a + j  # this row holds epoch k's (from epoch k+1's step)
                delta[k] = d0[j] - G[j] @ delta[k + 1]
                S = RRt[j] + G[j] @ S @ G[j].T
                S = 0.5 * (S + S.T)
                var[k] = np.diag(S)
                if cov is not None:
                    cov[k] = S
    return ChainSolution(delta, var, cost0, cost, cov)
