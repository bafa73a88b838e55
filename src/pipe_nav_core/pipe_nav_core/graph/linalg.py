"""Compiled small dense algebra of the batch solve (:mod:`.solver`): triangular inverses and
whiteners of stacks of small matrices, and the back-substitution's recursion over a piece of
epochs, loops that numpy and LAPACK would run one small matrix per call (their call costs
more than the work at the solver's sizes, 38 error states).

Units are those of the matrices given; nothing here knows of frames.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.jit import kernel
from pipe_nav_core.smooth.rts import cholesky_k

Array = NDArray[np.float64]


@kernel
def _inv_lower(L: Array, W: Array) -> None:
    """W = L^-1 for a lower triangular L (m, m) (its upper triangle not read; W's set to
    zero): forward substitution, column by column."""
    m = L.shape[0]
    for j in range(m):
        for i in range(j):
            W[i, j] = 0.0
        W[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, m):
            t = 0.0
            for k in range(j, i):
                t += L[i, k] * W[k, j]
            W[i, j] = -t / L[i, i]


@kernel(nogil=True)
def inv_lower_k(L: Array, W: Array) -> None:
    """W[b] = L[b]^-1 for a stack of lower triangular L (B, m, m) (upper triangles not
    read)."""
    for b in range(L.shape[0]):
        _inv_lower(L[b], W[b])


@kernel(nogil=True)
def whiteners_k(C: Array, floor: Array, W: Array) -> bool:
    """W[b] (m, m), lower triangular, with W C' W^T = I for each covariance of the stack C
    (B, m, m), where C' is C[b] made symmetric (the mean of it and its transpose) with its
    diagonal raised to floor[b] where not above it: the inverse of C''s lower Cholesky
    factor. False (W unfinished) when one of them is not positive definite."""
    m = C.shape[1]
    L = np.empty((m, m))
    for b in range(C.shape[0]):
        for i in range(m):
            for j in range(i + 1):
                L[i, j] = 0.5 * (C[b, i, j] + C[b, j, i])
            if L[i, i] <= floor[b]:
                L[i, i] = floor[b]
        if not cholesky_k(L, L):  # in L's lower triangle
            return False
        _inv_lower(L, W[b])
    return True


@kernel(nogil=True)
def back_substitute_k(
    G: Array, d0: Array, RRt: Array, S: Array, delta: Array, var: Array, cov: Array, k0: int
) -> None:
    """The back-substitution over a piece of epochs k0 .. k0 + B - 1, last first, given
    delta[k0 + B] and its marginal covariance S (n, n): delta_k = d0_k - G_k delta_{k+1} and
    Sigma_k = RRt_k + G_k Sigma_{k+1} G_k^T (made symmetric) for G, RRt (B, n, n), d0 (B, n)
    (:meth:`.solver.Eliminator.finish`); delta and var (K, n) get each epoch's row, cov (K,
    n, n) its covariance unless it is empty; S ends as epoch k0's."""
    full = cov.shape[0] > 0
    for j in range(G.shape[0] - 1, -1, -1):
        k = k0 + j
        Gj = G[j]
        delta[k] = d0[j] - Gj @ delta[k + 1]
        T = RRt[j] + Gj @ S @ Gj.T
        S[:] = 0.5 * (T + T.T)
        for i in range(S.shape[0]):
            var[k, i] = S[i, i]
        if full:
            cov[k] = S
