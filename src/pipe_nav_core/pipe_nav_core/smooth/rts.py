"""The Rauch-Tung-Striebel smoother (seed 001) over a recorded forward filter, in error-state
form and compiled.

The filter's state after each update is the linearization point, so the filtered error is
zero and the smoothed error is carried back through the gains. :func:`rts_packed` reads the
epochs in the packed form a Recording stores them in (:class:`EpochRows`: upper triangles of
the covariances, the non-identity rows of the transition), newest chunk first; :func:`rts`
packs lists of matrices for it, which is how the tests check it against batch least squares.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.jit import kernel

Array = NDArray[np.float64]


class EpochRows:
    """The packed form of one epoch that :func:`rts_packed` reads: one float64 row of
    ``width`` values, [upper triangle of P_upd | upper triangle of P_pred | Phi[phi_rows]],
    triangles row-major (the order of np.triu_indices), Phi rows row-major. The rows of Phi
    not in phi_rows are the identity's (n: error-state size; phi_rows: sorted row indices).

    constants: error states outside phi_rows whose process noise is zero, or a regularizer
    far below their variance (random constants). Column s of Phi P_upd is then column s of
    P_pred, so the transposed gain P_pred^-1 Phi P_upd has the unit vector e_s as column s:
    the smoother solves and multiplies out only the other columns (``dynamic``), in every
    epoch where the stored covariances show it (a marker epoch whose covariance the filter
    inflated or turned does not: its gain is solved whole).
    """

    def __init__(self, n: int, phi_rows: Sequence[int], constants: Sequence[int] = ()) -> None:
        self.n = n
        self.phi_rows = np.asarray(phi_rows, dtype=np.int64)
        if set(constants) & set(self.phi_rows.tolist()):
            raise ValueError("a random-constant error state cannot have a row of Phi stored")
        self.constants = np.unique(np.asarray(constants, dtype=np.int64))
        self.dynamic = np.setdiff1d(np.arange(n), self.constants)
        self.m = n * (n + 1) // 2
        self.width = 2 * self.m + len(self.phi_rows) * n
        self.iu = np.triu_indices(n)
        self.diag = np.cumsum(np.r_[0, np.arange(n, 1, -1)])  # of (i, i) in a triangle

    def pack(self, out: Array, P_upd: Array, P_pred: Array, phi: Array) -> None:
        """Write B epochs' (B, n, n) matrices into the rows out (B, width). ValueError if a
        row of phi outside phi_rows is not the identity's (it would be lost)."""
        mats = [np.ascontiguousarray(x, dtype=np.float64) for x in (P_upd, P_pred, phi)]
        if not _pack(*mats, self.phi_rows, out):
            raise ValueError("a row of Phi outside the stored rows differs from the identity")

    def covariances(self, rows: Array, which: str = "upd") -> Array:
        """The (B, n, n) covariances P_upd ("upd") or P_pred ("pred") of rows (B, width)."""
        seg = rows[:, : self.m] if which == "upd" else rows[:, self.m : 2 * self.m]
        out = np.empty((len(rows), self.n, self.n))
        out[:, self.iu[0], self.iu[1]] = seg
        out[:, self.iu[1], self.iu[0]] = seg
        return out

    def transitions(self, rows: Array) -> Array:
        """The (B, n, n) transitions Phi of rows (B, width)."""
        out = np.tile(np.eye(self.n), (len(rows), 1, 1))
        out[:, self.phi_rows] = rows[:, 2 * self.m :].reshape(len(rows), -1, self.n)
        return out

    def variances(self, rows: Array) -> Array:
        """The diagonals (B, n) of the P_upd of rows (B, width)."""
        return rows[:, self.diag]


@kernel(nogil=True)
def _pack(P_upd: Array, P_pred: Array, phi: Array, phi_rows: NDArray[np.int64], out: Array) -> bool:
    """EpochRows.pack; False if a row of phi outside phi_rows is not the identity's."""
    B, n = P_upd.shape[0], P_upd.shape[1]
    m = n * (n + 1) // 2
    stored = np.zeros(n, dtype=np.bool_)
    stored[phi_rows] = True
    for b in range(B):
        idx = 0
        for i in range(n):
            for j in range(i, n):
                out[b, idx] = P_upd[b, i, j]
                out[b, m + idx] = P_pred[b, i, j]
                idx += 1
        for a in range(phi_rows.shape[0]):
            for j in range(n):
                out[b, 2 * m + a * n + j] = phi[b, phi_rows[a], j]
        for i in range(n):
            if not stored[i]:
                for j in range(n):
                    if phi[b, i, j] != (1.0 if i == j else 0.0):
                        return False
    return True


@kernel
def _unpack(row: Array, start: int, P: Array) -> None:
    """P (n, n) <- the symmetric matrix whose upper triangle is row[start:] (row-major)."""
    n = P.shape[0]
    idx = start
    for i in range(n):
        for j in range(i, n):
            P[i, j] = row[idx]
            P[j, i] = row[idx]
            idx += 1


@kernel
def cholesky_k(A: Array, L: Array) -> bool:
    """L <- the lower Cholesky factor of A (symmetric, lower triangle read; L may be A itself:
    in place); False if A is not positive definite.

    Written out with :func:`_cho_solve` because, at the error-state sizes here (21 to 42),
    they take half the time of numba's np.linalg.solve (its LAPACK call copies and pivots);
    with it the whole smoother was 12 % slower. Right-looking: each column, once made,
    is taken off the rest of the triangle along contiguous rows, which the compiler
    vectorizes (the sums of the column-by-column form cannot be reordered); every entry
    sees the same subtractions in the same order, so the factor is the same to the bit."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            L[i, j] = A[i, j]
    col = np.empty(n)
    for j in range(n):
        s = L[j, j]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            L[i, j] = L[i, j] / d
            col[i] = L[i, j]
        for i in range(j + 1, n):
            f = L[i, j]
            for k in range(j + 1, i + 1):
                L[i, k] -= f * col[k]
    return True


@kernel
def _cho_solve(L: Array, B: Array) -> None:
    """B <- (L L^T)^-1 B in place (L lower triangular (n, n), B (n, m))."""
    n, m = B.shape
    for i in range(n):
        for p in range(i):
            f = L[i, p]
            for c in range(m):
                B[i, c] -= f * B[p, c]
        inv = 1.0 / L[i, i]
        for c in range(m):
            B[i, c] *= inv
    for i in range(n - 1, -1, -1):
        for p in range(i + 1, n):
            f = L[p, i]
            for c in range(m):
                B[i, c] -= f * B[p, c]
        inv = 1.0 / L[i, i]
        for c in range(m):
            B[i, c] *= inv


# how closely P_pred must agree with Phi P_upd Phi^T in the columns of the random constants
# for their gain columns to be taken as unit vectors: their own variance may have grown by their
# regularizing process noise (on the 10 km line under 3e-8 of it in 99.9 % of the epochs), the
# rest agree to round-off. A marker's covariance inflation or heading rotation fails it by far
# (4 epochs of 53612 there); the smoothed centrelines of the test pipes move by 1-2 nm.
CONSTANT_GROWTH = 1e-6
CONSTANT_COUPLING = 1e-9


@kernel
def _phi_p_columns(
    Pu: Array, phi_r: Array, phi_rows: NDArray[np.int64], cols: NDArray[np.int64], X: Array
) -> None:
    """X (n, len(cols)) <- the columns cols of Phi P_upd (the rows of Phi outside phi_rows,
    whose rows phi_r holds, are the identity's)."""
    n, d = X.shape
    for j in range(n):
        for c in range(d):
            X[j, c] = Pu[j, cols[c]]
    Bp = np.dot(phi_r, X)
    for a in range(phi_rows.shape[0]):
        X[phi_rows[a], :] = Bp[a]


@kernel
def _constants_hold(Pp: Array, Bc: Array, constants: NDArray[np.int64]) -> bool:
    """Whether the columns of the random constants of P_pred are those of Phi P_upd, Bc
    (n, constants) (within CONSTANT_GROWTH of their variance on the diagonal,
    CONSTANT_COUPLING of the correlation scale elsewhere): then their gain columns are unit
    vectors (EpochRows)."""
    for q in range(constants.shape[0]):
        s = constants[q]
        for j in range(Pp.shape[0]):
            diff = Pp[j, s] - Bc[j, q]
            if j == s:
                if not abs(diff) <= CONSTANT_GROWTH * Pp[s, s]:
                    return False
            elif not diff * diff <= CONSTANT_COUPLING**2 * (Pp[j, j] * Pp[s, s]):
                return False
    return True


@kernel
def _gain_columns(
    Pu: Array,
    Pp: Array,
    phi_r: Array,
    phi_rows: NDArray[np.int64],
    cols: NDArray[np.int64],
    L: Array,
    X: Array,
) -> None:
    """X (n, len(cols)) <- the columns cols of P_pred^-1 Phi P_upd (L: (n, n) room for the
    Cholesky factor)."""
    _phi_p_columns(Pu, phi_r, phi_rows, cols, X)
    if cholesky_k(Pp, L):
        _cho_solve(L, X)
    elif np.all(np.isfinite(Pp)):  # singular or indefinite: least squares
        X[:, :] = np.linalg.lstsq(Pp, X)[0]
    else:  # a diverged filter: its smoothing is undefined too
        X[:, :] = np.nan


@kernel
def _reduced(G: Array, d: int) -> Array:
    """The (n, d) gain columns kept at the start of the room G (n, n) of one epoch."""
    n = G.shape[0]
    return G.reshape(n * n)[: n * d].reshape((n, d))


@kernel(nogil=True)
def _rts_gains(
    rows: Array,
    next_row: Array,
    phi_rows: NDArray[np.int64],
    dynamic: NDArray[np.int64],
    constants: NDArray[np.int64],
    G: Array,
    whole: NDArray[np.bool_],
) -> None:
    """The transposed RTS gain P_pred[k+1]^-1 Phi[k+1] P_upd[k] of the epoch of rows[i]
    (EpochRows form), for every row that has a next epoch (rows[i + 1], or next_row for the
    last; next_row empty: the last row is the last epoch, G[-1] untouched): where the random
    constants' gain columns are unit vectors (:func:`_constants_hold`), only its ``dynamic``
    columns (n, d) at the start of G[i] and whole[i] False; else the whole gain in G[i]
    (n, n) and whole[i] True."""
    n = G.shape[1]
    m = n * (n + 1) // 2
    r = phi_rows.shape[0]
    every = np.arange(n)
    Pu, Pp, L = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    phi_r, Bc = np.empty((r, n)), np.empty((n, constants.shape[0]))
    for i in range(rows.shape[0]):
        nxt = rows[i + 1] if i + 1 < rows.shape[0] else next_row
        if nxt.shape[0] == 0:
            continue
        _unpack(rows[i], 0, Pu)
        _unpack(nxt, m, Pp)
        for a in range(r):
            for j in range(n):
                phi_r[a, j] = nxt[2 * m + a * n + j]
        _phi_p_columns(Pu, phi_r, phi_rows, constants, Bc)
        reduced = constants.shape[0] > 0 and _constants_hold(Pp, Bc, constants)
        whole[i] = not reduced
        if reduced:
            _gain_columns(Pu, Pp, phi_r, phi_rows, dynamic, L, _reduced(G[i], dynamic.shape[0]))
        else:
            _gain_columns(Pu, Pp, phi_r, phi_rows, every, L, G[i])


@kernel(nogil=True)
def _rts_backward(
    rows: Array,
    k0: int,
    G: Array,
    whole: NDArray[np.bool_],
    dx: Array,
    e: Array,
    var: Array,
    var_cols: NDArray[np.int64],
    P_full: Array,
    Ps: Array,
    Pp: Array,
    dynamic: NDArray[np.int64],
) -> None:
    """The RTS recursion over the epochs k0 .. k0 + len(rows) - 1 (rows in the EpochRows form,
    G and whole from :func:`_rts_gains`), from the last to the first. Carried between calls
    (in place): Ps and Pp, the smoothed and the predicted covariance of the epoch after the
    rows. Writes e[k], var[k] (the variances of the error states var_cols) and, if P_full has
    rows, P_full[k]."""
    n = Ps.shape[0]
    m = n * (n + 1) // 2
    K = e.shape[0]
    every = np.arange(n)
    Pu, D, v = np.empty((n, n)), np.empty((n, n)), np.empty(n)
    for i in range(rows.shape[0] - 1, -1, -1):
        k = k0 + i
        row = rows[i]
        _unpack(row, 0, Pu)
        if k == K - 1:
            Ps[:, :] = Pu
            e[k, :] = 0.0
        else:
            cols = every if whole[i] else dynamic
            d = cols.shape[0]
            X = G[i] if whole[i] else _reduced(G[i], d)  # the columns cols of G^T
            # e[k] = G v, v = e[k+1] + dx[k+1], G's rows outside cols the identity's
            for p in range(n):
                v[p] = e[k + 1, p] + dx[k + 1, p]
                e[k, p] = v[p]
            for c in range(d):
                acc = 0.0
                for p in range(n):
                    acc += X[p, c] * v[p]
                e[k, cols[c]] = acc
            # Ps[k] = P_upd[k] + G (Ps[k+1] - P_pred[k+1]) G^T, symmetrized: D where both
            # states are outside cols, (X^T D)[c, b] where one is, X^T D X where both are
            for a in range(n):
                for b in range(n):
                    D[a, b] = Ps[a, b] - Pp[a, b]
            GD = np.dot(X.T, D)
            GDG = np.dot(GD, X)
            for a in range(n):
                for b in range(a, n):
                    x = 0.5 * ((Pu[a, b] + D[a, b]) + (Pu[b, a] + D[b, a]))
                    Ps[a, b] = x
                    Ps[b, a] = x
            for c in range(d):
                a = cols[c]
                for b in range(n):
                    x = Pu[a, b] + GD[c, b]
                    Ps[a, b] = x
                    Ps[b, a] = x
            for c in range(d):
                a = cols[c]
                for c2 in range(c, d):
                    b = cols[c2]
                    x = 0.5 * ((Pu[a, b] + GDG[c, c2]) + (Pu[b, a] + GDG[c2, c]))
                    Ps[a, b] = x
                    Ps[b, a] = x
        for c in range(var_cols.shape[0]):
            var[k, c] = Ps[var_cols[c], var_cols[c]]
        if P_full.shape[0]:
            P_full[k] = Ps
        _unpack(row, m, Pp)


PIECE_EPOCHS = 512  # epochs per call of the RTS kernels
# threads making the gains: a part of a piece each, beside the recursion of the piece after it
# (the gains are two thirds of the work: one thread left them the critical path)
GAIN_THREADS = 2


def rts_packed(
    chunks: Iterable[tuple[int, Array]],
    dx: Array,
    fmt: EpochRows,
    *,
    full: bool = False,
    var_cols: Sequence[int] | NDArray[np.int64] | None = None,
) -> tuple[Array, Array]:
    """Error-state RTS smoother over packed epochs, compiled.

    chunks: (index of the first epoch, rows (C, fmt.width)) from the last epochs to the
    first, contiguous, covering epochs 0 .. K - 1 (a recording too large for memory is read
    back chunk by chunk); epoch k's row holds P_upd[k] and (for k >= 1) P_pred[k] and Phi
    from k-1 to k; dx (K, n): dx[k] = x_upd[k] (-) x_pred[k]. The gain
    G = P_upd[k] Phi^T P_pred[k+1]^-1 is solved through a Cholesky factor of P_pred; the gains
    of the next piece of epochs are computed in GAIN_THREADS threads while the recursion runs.
    Returns e (K, n): the smoothed correction to x_upd[k], and the smoothed variances (K, n)
    (in the error state's units; with var_cols, (K, len(var_cols)) of those error states
    only), or with full=True the smoothed covariances (K, n, n).
    """
    dx = np.ascontiguousarray(dx, dtype=np.float64)
    K, n = dx.shape
    cols = np.arange(n) if var_cols is None else np.asarray(var_cols, dtype=np.int64)
    e = np.zeros((K, n))
    var = np.zeros((K, len(cols)))
    P_full = np.zeros((K if full else 0, n, n))
    Ps, Pp = np.zeros((n, n)), np.zeros((n, n))
    gains = [np.empty((PIECE_EPOCHS, n, n)) for _ in range(2)]
    wholes = [np.zeros(PIECE_EPOCHS, dtype=np.bool_) for _ in range(2)]
    pieces = (
        (k0 + a, np.ascontiguousarray(rows[a : a + PIECE_EPOCHS], dtype=np.float64))
        for k0, rows in chunks
        for a in range(((len(rows) - 1) // PIECE_EPOCHS) * PIECE_EPOCHS, -1, -PIECE_EPOCHS)
    )
    end, next_row = K, np.zeros(0)
    pending: tuple[int, Array, list[Future[None]], Array, NDArray[np.bool_]] | None = None
    with ThreadPoolExecutor(max_workers=GAIN_THREADS) as pool:
        for b, (k0, rows) in enumerate(pieces):
            if k0 + len(rows) != end or not len(rows):
                raise ValueError("rts_packed: chunks must run from the last epoch back")
            G, W = gains[b % 2], wholes[b % 2]
            # a part of the rows per thread (the gain of a part's last row needs the first
            # row after it)
            cuts = sorted({len(rows) * j // GAIN_THREADS for j in range(GAIN_THREADS + 1)})
            jobs = [pool.submit(_rts_gains, rows[i:j], rows[j] if j < len(rows) else next_row,
                                fmt.phi_rows, fmt.dynamic, fmt.constants, G[i:j], W[i:j])
                    for i, j in zip(cuts[:-1], cuts[1:], strict=True)]  # fmt: skip
            if pending is not None:  # the piece after this one, while its gains are made
                _recursion(pending, dx, e, var, cols, P_full, Ps, Pp, fmt.dynamic)
            pending = (k0, rows, jobs, G, W)
            end, next_row = k0, rows[0]
        if pending is not None:
            _recursion(pending, dx, e, var, cols, P_full, Ps, Pp, fmt.dynamic)
    if end != 0:
        raise ValueError("rts_packed: the chunks do not reach epoch 0")
    return e, (P_full if full else var)


def _recursion(
    piece: tuple[int, Array, list[Future[None]], Array, NDArray[np.bool_]], *arrays: Array
) -> None:
    k0, rows, jobs, G, W = piece
    for job in jobs:
        job.result()
    _rts_backward(rows, k0, G, W, *arrays)


def rts(
    P_upd: Sequence[Array],
    P_pred: Sequence[Array],
    phi: Sequence[Array],
    dx: Sequence[Array],
    *,
    full: bool = True,
) -> tuple[Array, Array]:
    """:func:`rts_packed` over lists of matrices: epoch k has the updated covariance P_upd[k],
    and (for k >= 1) the predicted covariance P_pred[k], the transition phi[k] from k-1 to k,
    and dx[k] = x_upd[k] (-) x_pred[k]. Returns e (K, n) and the smoothed covariances
    (K, n, n), or with full=False their diagonals (K, n)."""
    K = len(P_upd)
    n = np.shape(P_upd[0])[0]
    fmt = EpochRows(n, range(n))
    rows = np.empty((K, fmt.width))
    fmt.pack(rows, P_upd, [P_upd[0], *P_pred[1:]], [np.eye(n), *phi[1:]])
    return rts_packed([(0, rows)], np.asarray(dx, dtype=np.float64).reshape(K, n), fmt, full=full)
