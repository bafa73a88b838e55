"""The batch (factor-graph) solver on linear Gaussian chains: it equals the RTS smoother and
dense batch least squares to round-off, also with nearly constant states."""

from dataclasses import replace

import numpy as np
import pytest
from pipe_nav_core.graph.batch import StreamingSolve, factor_weights
from pipe_nav_core.graph.linalg import back_substitute_k
from pipe_nav_core.graph.problem import LinearChain, MeasurementFactor, Prior, whitener
from pipe_nav_core.graph.robust import cauchy_weight, huber_cost, huber_weight
from pipe_nav_core.graph.solver import PIECE, inv_triangular, solve_chain, whiten, whiteners
from pipe_nav_core.smooth.rts import rts


def _no_model(sv, L):  # noqa: ANN001, ANN202
    raise AssertionError("a linear toy factor is never relinearized")


def _toy(seed: int, K: int = 60, tiny: float | None = None):
    """A random linear chain: n = 5 states (position/velocity pairs and one constant-ish
    parameter), 1 to 2 measurement rows per epoch, some epochs without any."""
    rng = np.random.default_rng(seed)
    n = 5
    phi = np.zeros((K, n, n))
    qd = np.zeros((K, n, n))
    off = np.zeros((K, n))
    for k in range(1, K):
        F = np.eye(n) + 0.1 * rng.standard_normal((n, n)) * (rng.random((n, n)) < 0.4)
        F[4] = np.eye(n)[4]  # the parameter stays (a random walk)
        phi[k] = F
        B = 0.1 * rng.standard_normal((n, n))
        q = B @ B.T + np.diag([1e-3, 2e-3, 1e-3, 2e-3, 1e-4])
        if tiny is not None:
            q[4, :] = q[:, 4] = 0.0
            q[4, 4] = tiny
        qd[k] = q
        off[k] = 0.05 * rng.standard_normal(n)
        if tiny is not None:
            off[k, 4] = 0.0  # the linearization point holds the parameter constant too
    P0 = np.diag([1.0, 0.5, 1.0, 0.5, 0.3])
    x0 = rng.standard_normal(n) * 0.2
    factors = []
    for k in range(K):
        for _ in range(int(rng.integers(0, 3))):
            m = int(rng.integers(1, 3))
            H = rng.standard_normal((m, n))
            A = rng.standard_normal((m, m))
            R = 0.1 * (A @ A.T + np.eye(m))
            r = rng.standard_normal(m)
            factors.append(MeasurementFactor("toy", k, r, H, R, _no_model))
    return LinearChain.dense(Prior(x0, P0), phi, qd, off, factors)


def _kalman_rts(chain: LinearChain):
    """Forward Kalman filter over the chain, then smooth.rts.rts: (mean, covariances)."""
    n = chain.n
    groups = chain.by_epoch()
    x, P = chain.prior.x0.copy(), chain.prior.P0.copy()
    P_upd, P_pred, phis, dxs, xs = [], [], [], [], []
    for k in range(chain.K):
        if k:
            x = chain.phi[k] @ x + chain.offset[k]
            P = chain.phi[k] @ P @ chain.phi[k].T + chain.qd[k]
        P_pred.append(P.copy())
        x_pred = x.copy()
        for i in groups[k]:
            f = chain.factors[i]
            S = f.H @ P @ f.H.T + f.R
            G = P @ f.H.T @ np.linalg.inv(S)
            x = x + G @ (f.r - f.H @ x)
            IKH = np.eye(n) - G @ f.H
            P = IKH @ P @ IKH.T + G @ f.R @ G.T
        P_upd.append(P.copy())
        phis.append(chain.phi[k] if k else np.eye(n))
        dxs.append(x - x_pred)
        xs.append(x.copy())
    e, cov = rts(P_upd, P_pred, phis, dxs)
    return np.array(xs) + e, cov


def _dense(chain: LinearChain):
    """Dense weighted least squares over all epochs (information form)."""
    K, n = chain.K, chain.n
    N = K * n
    A = np.zeros((N, N))
    b = np.zeros(N)
    P0i = np.linalg.inv(chain.prior.P0)
    A[:n, :n] += P0i
    b[:n] += P0i @ chain.prior.x0
    for f in chain.factors:
        sl = slice(f.epoch * n, (f.epoch + 1) * n)
        Ri = np.linalg.inv(f.R)
        A[sl, sl] += f.H.T @ Ri @ f.H
        b[sl] += f.H.T @ Ri @ f.r
    for k in range(1, K):
        Qi = np.linalg.inv(chain.qd[k])
        F, o = chain.phi[k], chain.offset[k]
        pr, sl = slice((k - 1) * n, k * n), slice(k * n, (k + 1) * n)
        A[pr, pr] += F.T @ Qi @ F
        A[sl, sl] += Qi
        A[pr, sl] -= F.T @ Qi
        A[sl, pr] -= Qi @ F
        b[sl] += Qi @ o
        b[pr] -= F.T @ Qi @ o
    cov = np.linalg.inv(A)
    return np.linalg.solve(A, b).reshape(K, n), cov


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_graph_equals_rts_and_batch_on_a_linear_toy(seed: int) -> None:
    chain = _toy(seed)
    sol = solve_chain(chain, full=True)
    x_rts, P_rts = _kalman_rts(chain)
    x_lsq, cov = _dense(chain)
    scale = np.abs(x_lsq).max()
    assert np.abs(sol.delta - x_rts).max() < 1e-10 * scale
    assert np.abs(sol.delta - x_lsq).max() < 1e-10 * scale
    assert sol.cov is not None
    assert np.abs(sol.cov - P_rts).max() < 1e-10 * np.abs(P_rts).max()
    n = chain.n
    for k in (0, chain.K // 2, chain.K - 1):
        blk = cov[k * n : (k + 1) * n, k * n : (k + 1) * n]
        assert np.allclose(sol.cov[k], blk, rtol=1e-9, atol=1e-12)
    assert np.allclose(sol.var, np.diagonal(P_rts, axis1=1, axis2=2), rtol=1e-9)
    # the cost the linear model reaches is the minimum of the cost at zero
    assert 0.0 < sol.cost < sol.cost0


def test_graph_resolves_nearly_constant_states_like_rts() -> None:
    """A parameter with process noise 1e-19 per epoch (as the filter's misalignment states):
    the normal equations lose it in double precision, the QR elimination does not."""
    chain = _toy(7, K=200, tiny=1e-19)
    sol = solve_chain(chain)
    x_rts, _ = _kalman_rts(chain)
    assert np.abs(sol.delta - x_rts).max() < 1e-8 * np.abs(x_rts).max()
    # the parameter is one value over the run, as its dynamics say
    assert np.ptp(sol.delta[:, 4]) < 1e-6 * max(abs(sol.delta[0, 4]), 1e-3)


def test_weights_scale_and_remove_factors() -> None:
    chain = _toy(4, K=30)
    w = np.ones(len(chain.factors))
    w[0] = 0.0  # left out
    w[1] = 0.25  # noise four times larger
    sol = solve_chain(chain, w)
    f0, f1 = chain.factors[0], chain.factors[1]
    keep = [f for i, f in enumerate(chain.factors) if i != 0]
    keep[0] = MeasurementFactor(f1.kind, f1.epoch, f1.r, f1.H, 4.0 * f1.R, _no_model)
    ref = solve_chain(replace(chain, factors=keep))
    assert f0.epoch >= 0
    assert np.abs(sol.delta - ref.delta).max() < 1e-12 * np.abs(ref.delta).max()


def test_whitener_and_robust_weights() -> None:
    C = np.array([[4.0, 1.0], [1.0, 2.0]])
    W = whitener(C)
    assert np.allclose(W @ C @ W.T, np.eye(2))
    S = np.diag([1.0, 0.0])  # singular: floored, still finite
    assert np.all(np.isfinite(whitener(S)))
    assert np.allclose(huber_weight([0.5, 3.0, 6.0]), [1.0, 1.0, 0.5])
    assert np.allclose(huber_cost([1.0, 6.0]), [1.0, 2 * 3.0 * 6.0 - 9.0])
    assert cauchy_weight(30.0) < 0.011


def test_batched_whitening_matches_each_factor() -> None:
    chain = _toy(5, K=20)
    exact = MeasurementFactor("toy", 3, np.ones(2), np.ones((2, 5)), np.diag([0.0, 1.0]), _no_model)
    factors = [*chain.factors, exact]
    wf = whiten(factors, chain.n)
    for i, f in enumerate(factors):
        assert np.isclose(wf.norm[i], f.whitened_norm(), rtol=1e-12)
        assert wf.exact[i] == f.exact
        rows = wf.rows[wf.start[np.flatnonzero(wf.order == i)[0]] :][: len(f.r)]
        assert np.allclose(rows, whitener(f.R) @ f.H, rtol=1e-12, atol=1e-12)
    assert wf.exact[-1] and not wf.exact[:-1].any()
    assert np.all(np.diff(wf.epochs) >= 0)


def test_triangular_inverses_and_batched_whiteners() -> None:
    """inv_triangular (compiled substitution, reading one triangle) equals the general inverse
    to round-off; whiteners (compiled) equal whitener one by one, diagonal, full and singular,
    and so does their fallback when one covariance is not positive definite."""
    rng = np.random.default_rng(11)
    U = np.triu(rng.standard_normal((7, 9, 9))) + 4.0 * np.eye(9)
    junk = U + np.tril(rng.standard_normal((7, 9, 9)), -1)  # below the diagonal: not read
    for T, lower in ((U, False), (np.swapaxes(U, 1, 2), True)):
        ref = np.linalg.inv(T)
        inv = inv_triangular(junk if not lower else np.swapaxes(junk, 1, 2), lower=lower)
        assert np.allclose(inv, ref, rtol=1e-13, atol=1e-13)
        assert np.all((np.tril(inv, -1) if not lower else np.triu(inv, 1)) == 0.0)
    A = rng.standard_normal((5, 4, 4))
    diagonal = np.diag([1e-6, 2.0, 3.0, 1e2])[None]
    singular = np.diag([0.0, 1.0, 2.0, 3.0])[None]
    C = np.concatenate([A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(4), diagonal, singular])
    W = whiteners(C)
    for c, w in zip(C, W, strict=True):
        assert np.allclose(w, whitener(c), rtol=1e-12, atol=1e-12 * np.abs(w).max())
    indefinite = np.eye(4)[None].copy()
    indefinite[0, 0, 1] = indefinite[0, 1, 0] = 2.0
    C = np.concatenate([C, indefinite])
    for c, w in zip(C, whiteners(C), strict=True):
        assert np.array_equal(w, whitener(c))


def test_compiled_back_substitution_is_the_recursion() -> None:
    """linalg.back_substitute_k equals the back-substitution's recursion written out with
    numpy epoch by epoch (round-off): delta_k = d0_k - G_k delta_{k+1}, Sigma_k = RRt_k +
    G_k Sigma_{k+1} G_k^T; the covariances only where asked for."""
    rng = np.random.default_rng(4)
    B, n, k0 = 7, 5, 3
    K = k0 + B + 1
    G = 0.3 * rng.standard_normal((B, n, n))
    d0 = rng.standard_normal((B, n))
    A = rng.standard_normal((B, n, n))
    RRt = A @ np.swapaxes(A, 1, 2)
    S0 = np.eye(n) + 0.1 * np.ones((n, n))
    delta, var, cov = np.zeros((K, n)), np.zeros((K, n)), np.zeros((K, n, n))
    delta[-1] = rng.standard_normal(n)
    S = S0.copy()
    back_substitute_k(G, d0, RRt, S, delta, var, cov, k0)
    d, want = delta[-1].copy(), S0.copy()
    for j in range(B - 1, -1, -1):
        d = d0[j] - G[j] @ d
        T = RRt[j] + G[j] @ want @ G[j].T
        want = 0.5 * (T + T.T)
        assert np.allclose(delta[k0 + j], d, rtol=1e-13, atol=1e-13)
        assert np.allclose(cov[k0 + j], want, rtol=1e-13, atol=1e-13)
        assert np.array_equal(var[k0 + j], np.diag(cov[k0 + j]))
    assert np.array_equal(S, cov[k0]) and not delta[:k0].any() and not cov[:k0].any()
    var2 = np.zeros((K, n))
    back_substitute_k(G, d0, RRt, S0.copy(), delta.copy(), var2, np.empty((0, n, n)), k0)
    assert np.array_equal(var2, var)


@pytest.mark.parametrize("seed", [1, 2])
def test_streaming_solve_in_pieces_equals_the_batch_solve(seed: int) -> None:
    """StreamingSolve (epochs whitened and weighed PIECE at a time, then eliminated with
    LAPACK's QR) equals solve_chain with factor_weights' weights to round-off, over more than
    one piece, with a gated factor, a downweighted robust one and an exact one."""
    chain = _toy(seed, K=PIECE + 137)
    f = chain.factors
    f[3] = replace(f[3], r=100.0 * f[3].r / np.linalg.norm(f[3].r))  # far outside the gate
    f[5] = replace(f[5], r=40.0 * f[5].r / np.linalg.norm(f[5].r), robust=True, name="m1")
    f[8] = replace(f[8], R=np.diag(np.r_[0.0, np.ones(len(f[8].r) - 1)]))  # a constraint
    f.sort(key=lambda x: x.epoch)
    w, weighing, _ = factor_weights(chain, 0.9999)
    assert weighing.gated and weighing.downweighted == ["m1"]
    whole = solve_chain(chain, w)
    stream = StreamingSolve(chain.n, 0.9999)
    groups = chain.by_epoch()
    stream.start(chain.prior, [f[i] for i in groups[0]])
    for k in range(1, chain.K):
        phi, qd = chain.transitions(k, k + 1)[0], chain.process_noise(k, k + 1)[0]
        stream.epoch(phi, qd, chain.offset[k], [f[i] for i in groups[k]])
    sol, wg = stream.finish()
    scale = np.abs(whole.delta).max()
    assert np.abs(sol.delta - whole.delta).max() < 1e-10 * scale
    assert np.allclose(sol.var, whole.var, rtol=1e-9, atol=0.0)
    assert wg.gated == weighing.gated and wg.downweighted == weighing.downweighted
    assert np.isclose(sol.cost0, whole.cost0, rtol=1e-12)
    assert np.isclose(sol.cost, whole.cost, rtol=1e-9)


def test_the_kept_rows_in_smaller_chunks_give_the_same_bytes(monkeypatch) -> None:
    """The eliminator keeps its rows for back-substitution in chunks of STORE_EPOCHS (a
    multiple of PIECE, fewer than the recording's: its rows are wide); over several chunks,
    spilled to disk or not, the solution is the same, bit for bit."""
    from pipe_nav_core.graph import solver

    chain = _toy(4, K=3 * PIECE + 137)
    ref = solve_chain(chain)
    monkeypatch.setattr(solver, "STORE_EPOCHS", PIECE)
    monkeypatch.setattr(solver, "RAM_BUDGET_BYTES", 0)  # all but two chunks spill
    small = solve_chain(chain)
    for a, b in ((ref.delta, small.delta), (ref.var, small.var)):
        assert a.tobytes() == b.tobytes()
    assert ref.cost == small.cost
    monkeypatch.undo()
    assert solver.STORE_EPOCHS % PIECE == 0
