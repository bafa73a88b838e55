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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .problem import LinearChain, whitener

Array = NDArray[np.float64]


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


def _rows(
    chain: LinearChain, groups: list[list[int]], k: int, weights: Array
) -> tuple[Array, Array]:
    """The whitened measurement rows (m, n) and right-hand side (m,) of epoch k."""
    n = chain.n
    blocks, rhs = [], []
    for i in groups[k]:
        f = chain.factors[i]
        w = float(weights[i])
        if w <= 0.0:
            continue
        V = whitener(f.R / w)
        blocks.append(V @ f.H)
        rhs.append(V @ f.r)
    if not blocks:
        return np.zeros((0, n)), np.zeros(0)
    return np.vstack(blocks), np.concatenate(rhs)


def _triangular(A: Array, rows: int) -> Array:
    """The upper triangular factor of A's QR, padded with zero rows to rows x A.shape[1]."""
    R = np.linalg.qr(A, mode="r")
    if R.shape[0] < rows:
        R = np.vstack([R, np.zeros((rows - R.shape[0], R.shape[1]))])
    return R[:rows]


def solve_chain(
    chain: LinearChain, weights: Array | None = None, *, full: bool = False
) -> ChainSolution:
    """Minimise the chain's weighted least-squares cost over every epoch's error state at once
    (see the module docstring). weights (F,): one per factor of chain.factors, dividing its
    noise covariance (IRLS weights of a robust loss; 0 leaves the factor out; default all 1).
    full: also return the marginal covariances (K, n, n)."""
    K, n = chain.K, chain.n
    w = np.ones(len(chain.factors)) if weights is None else np.asarray(weights, dtype=np.float64)
    groups = chain.by_epoch()
    Rkk = np.empty((K, n, n))
    Rkn = np.empty((K, n, n))
    zk = np.empty((K, n))
    cost0 = 0.0
    # epoch 0: the prior and its measurements
    W0 = whitener(chain.prior.P0)
    M, m = _rows(chain, groups, 0, w)
    A = np.vstack([np.c_[W0, W0 @ chain.prior.x0], np.c_[M, m]])
    cost0 += float(np.sum(A[:, -1] ** 2))
    T = _triangular(A, n + 1)
    Rt, zt = T[:n, :n], T[:n, n]
    cost = float(T[n, n] ** 2)
    for k in range(1, K):
        W = whitener(chain.qd[k])
        M, m = _rows(chain, groups, k, w)
        rows = 2 * n + len(m)
        A = np.zeros((rows, 2 * n + 1))
        A[:n, :n], A[:n, -1] = Rt, zt
        A[n : 2 * n, :n] = -W @ chain.phi[k]
        A[n : 2 * n, n : 2 * n] = W
        b = W @ chain.offset[k]
        A[n : 2 * n, -1] = b
        if len(m):
            A[2 * n :, n : 2 * n] = M
            A[2 * n :, -1] = m
        cost0 += float(b @ b + m @ m)
        T = _triangular(A, 2 * n + 1)
        Rkk[k - 1], Rkn[k - 1], zk[k - 1] = T[:n, :n], T[:n, n : 2 * n], T[:n, -1]
        Rt, zt = T[n : 2 * n, n : 2 * n], T[n : 2 * n, -1]
        cost += float(T[2 * n, -1] ** 2)
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
    for k in range(K - 2, -1, -1):
        Ri = np.linalg.inv(Rkk[k])
        G = Ri @ Rkn[k]
        delta[k] = Ri @ zk[k] - G @ delta[k + 1]
        S = Ri @ Ri.T + G @ S @ G.T
        S = 0.5 * (S + S.T)
        var[k] = np.diag(S)
        if cov is not None:
            cov[k] = S
    return ChainSolution(delta, var, cost0, cost, cov)
