"""Smoothers over a recorded forward filter.

- :func:`rts`: Rauch-Tung-Striebel (seed 001) in error-state form: the filter's state after
  each update is the linearization point, so the filtered error is zero and the smoothed
  error is carried back through the gains;
- :func:`backward_information` + :func:`fuse_information`: the two-filter smoother (seed 001
  RTS-FC, seed 004), forward estimate fused with a backward filter by inverse-covariance
  weighting; the backward filter is in information form so it starts without a prior;
- :func:`fuse_covariance`: the same fusion for a backward filter run in covariance form.

On a linear Gaussian problem both equal the batch least-squares solution (tests).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def rts(
    P_upd: Sequence[Array],
    P_pred: Sequence[Array],
    phi: Sequence[Array],
    dx: Sequence[Array],
    *,
    full: bool = True,
) -> tuple[Array, Array]:
    """Error-state RTS smoother.

    Epoch k has the updated covariance P_upd[k], and (for k >= 1) the predicted covariance
    P_pred[k], the transition phi[k] from k-1 to k, and dx[k] = x_upd[k] (-) x_pred[k].
    Returns e (K, n): the smoothed correction to x_upd[k], and the smoothed covariances
    P_s (K, n, n), or with full=False only their diagonals (K, n) (the variances, in the
    error state's units; a long run's K full covariances take gigabytes).
    """
    K = len(P_upd)
    n = P_upd[0].shape[0]
    e = np.zeros((K, n))
    out = np.empty((K, n, n) if full else (K, n))

    def keep(k: int, P: Array) -> None:
        out[k] = P if full else P.diagonal()

    P_next = P_upd[-1]
    keep(K - 1, P_next)
    for k in range(K - 2, -1, -1):
        Pp = P_pred[k + 1]
        try:
            G = np.linalg.solve(Pp, phi[k + 1] @ P_upd[k]).T
        except np.linalg.LinAlgError:
            G = np.linalg.lstsq(Pp, phi[k + 1] @ P_upd[k], rcond=None)[0].T
        e[k] = G @ (e[k + 1] + dx[k + 1])
        Ps = P_upd[k] + G @ (P_next - Pp) @ G.T
        P_next = 0.5 * (Ps + Ps.T)
        keep(k, P_next)
    return e, out


def backward_information(
    F: Sequence[Array],
    Q: Sequence[Array],
    H: Sequence[Array],
    R: Sequence[Array],
    z: Sequence[Array],
) -> tuple[Array, Array]:
    """Backward information filter of the linear model x[k+1] = F[k+1] x[k] + w (cov Q[k+1]),
    z[k] = H[k] x[k] + v (cov R[k]), started without prior at the last epoch.

    Returns (y, Y): information vector and matrix at each epoch k from the measurements
    AFTER k only (the backward prediction), ready for :func:`fuse_information`.
    """
    K = len(z)
    n = F[1].shape[0] if K > 1 else H[0].shape[1]
    y = np.zeros((K, n))
    Y = np.zeros((K, n, n))
    y_u = np.zeros(n)
    Y_u = np.zeros((n, n))
    for k in range(K - 1, -1, -1):
        y[k], Y[k] = y_u, Y_u
        Ri = np.linalg.inv(R[k])
        Y_k = Y_u + H[k].T @ Ri @ H[k]
        y_k = y_u + H[k].T @ Ri @ z[k]
        if k == 0:
            break
        M = np.linalg.solve((np.eye(n) + Y_k @ Q[k]).T, np.eye(n)).T  # (I + Y Q)^-1
        Y_u = F[k].T @ M @ Y_k @ F[k]
        Y_u = 0.5 * (Y_u + Y_u.T)
        y_u = F[k].T @ M @ y_k
    return y, Y


def fuse_information(x_f: Array, P_f: Array, y_b: Array, Y_b: Array) -> tuple[Array, Array]:
    """Fuse a forward estimate (x_f, P_f) with backward information (y_b, Y_b)."""
    Pi = np.linalg.inv(P_f)
    P = np.linalg.inv(Pi + Y_b)
    return P @ (Pi @ x_f + y_b), 0.5 * (P + P.T)


def fuse_covariance(x_f: Array, P_f: Array, x_b: Array, P_b: Array) -> tuple[Array, Array]:
    """Inverse-covariance weighting of two independent estimates of the same state
    (seed 001 eq. 29-30). Returns (x, P)."""
    S = P_f + P_b
    K = np.linalg.solve(S, P_f).T  # P_f (P_f + P_b)^-1
    x = x_f + K @ (x_b - x_f)
    P = P_f - K @ P_f
    return x, 0.5 * (P + P.T)
