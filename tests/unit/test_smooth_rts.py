"""The RTS smoother (smooth.rts) on linear Gaussian toy problems: it equals the batch
least-squares solution, and iterated about its own result it reaches the MAP of a nonlinear one."""

import numpy as np
import pytest
from pipe_nav_core.smooth.rts import rts


def _toy(seed: int = 3, K: int = 40):
    rng = np.random.default_rng(seed)
    n = 4
    dt = 0.5
    F = np.eye(n)
    F[0, 1] = F[2, 3] = dt
    Q = np.diag([1e-3, 2e-2, 1e-3, 2e-2])
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = np.diag([0.3, 0.2])
    x0 = np.array([0.0, 1.0, 2.0, -0.5])
    P0 = np.diag([1.0, 0.5, 1.0, 0.5])
    xs, zs = [], []
    x = x0 + rng.multivariate_normal(np.zeros(n), P0)
    for k in range(K):
        if k:
            x = F @ x + rng.multivariate_normal(np.zeros(n), Q)
        xs.append(x)
        zs.append(H @ x + rng.multivariate_normal(np.zeros(2), R))
    return F, Q, H, R, x0, P0, np.array(zs)


def _batch(F, Q, H, R, x0, P0, zs):
    """Weighted least squares over all states (information form), exact MAP."""
    K, n = len(zs), F.shape[0]
    N = K * n
    A = np.zeros((N, N))
    b = np.zeros(N)
    P0i, Qi, Ri = np.linalg.inv(P0), np.linalg.inv(Q), np.linalg.inv(R)
    A[:n, :n] += P0i
    b[:n] += P0i @ x0
    for k in range(K):
        sl = slice(k * n, (k + 1) * n)
        A[sl, sl] += H.T @ Ri @ H
        b[sl] += H.T @ Ri @ zs[k]
        if k:
            pr = slice((k - 1) * n, k * n)
            A[pr, pr] += F.T @ Qi @ F
            A[sl, sl] += Qi
            A[pr, sl] -= F.T @ Qi
            A[sl, pr] -= Qi @ F
    cov = np.linalg.inv(A)
    return np.linalg.solve(A, b).reshape(K, n), np.array(
        [cov[k * n : (k + 1) * n, k * n : (k + 1) * n] for k in range(len(zs))]
    )


def _forward(F, Q, H, R, x0, P0, zs):
    n = F.shape[0]
    x, P = x0.copy(), P0.copy()
    out = {"x": [], "P_upd": [], "P_pred": [], "phi": [], "dx": []}
    for k, z in enumerate(zs):
        if k:
            x = F @ x
            P = F @ P @ F.T + Q
        Pp = P.copy()
        S = H @ P @ H.T + R
        K_ = P @ H.T @ np.linalg.inv(S)
        dx = K_ @ (z - H @ x)
        x = x + dx
        P = (np.eye(n) - K_ @ H) @ P
        for key, v in zip(("x", "P_upd", "P_pred", "phi", "dx"), (x.copy(), P.copy(), Pp, F, dx)):
            out[key].append(v)
    return out


def test_rts_equals_batch_least_squares():
    F, Q, H, R, x0, P0, zs = _toy()
    fw = _forward(F, Q, H, R, x0, P0, zs)
    e, P_s = rts(fw["P_upd"], fw["P_pred"], fw["phi"], fw["dx"])
    x_s = np.array(fw["x"]) + e
    x_b, P_b = _batch(F, Q, H, R, x0, P0, zs)
    np.testing.assert_allclose(x_s, x_b, atol=1e-10)
    np.testing.assert_allclose(P_s, P_b, atol=1e-10)
    # and smoothing really changed something (the test could fail)
    assert np.abs(e[:-1]).max() > 1e-2


def test_rts_with_a_singular_or_diverged_prediction():
    """A state known exactly (zero variance, never driven) makes every P_pred singular: the
    gains fall back to least squares and the other states smooth as without it. A non-finite
    P_pred (a diverged filter) leaves the epochs before it undefined (NaN), not wrong."""
    F, Q, H, R, x0, P0, zs = _toy()
    fw = _forward(F, Q, H, R, x0, P0, zs)
    e4, P4 = rts(fw["P_upd"], fw["P_pred"], fw["phi"], fw["dx"])

    def grow(a):
        out = np.zeros((5, 5))
        out[:4, :4] = a
        return out

    phi5 = [grow(f) for f in fw["phi"]]
    for f in phi5:
        f[4, 4] = 1.0
    P_upd5 = [grow(a) for a in fw["P_upd"]]
    P_pred5 = [grow(a) for a in fw["P_pred"]]
    dx5 = [np.r_[d, 0.0] for d in fw["dx"]]
    e5, P5 = rts(P_upd5, P_pred5, phi5, dx5)
    assert np.all(np.isfinite(e5)) and np.all(np.isfinite(P5))
    np.testing.assert_allclose(e5[:, :4], e4, atol=1e-9)
    np.testing.assert_allclose(P5[:, :4, :4], P4, atol=1e-9)
    assert np.all(e5[:, 4] == 0.0)

    P_pred5[10] = np.full((5, 5), np.nan)
    e_nan, _ = rts(P_upd5, P_pred5, phi5, dx5)
    assert np.all(np.isnan(e_nan[9]))
    np.testing.assert_allclose(e_nan[10:, :4], e4[10:], atol=1e-9)


@pytest.mark.parametrize("seed", [1, 2])
def test_rts_reduces_error_on_average(seed):
    F, Q, H, R, x0, P0, zs = _toy(seed=seed, K=60)
    fw = _forward(F, Q, H, R, x0, P0, zs)
    e, P_s = rts(fw["P_upd"], fw["P_pred"], fw["phi"], fw["dx"])
    # smoothed covariance is never larger than the filtered one
    for k in range(len(zs)):
        assert np.all(np.linalg.eigvalsh(fw["P_upd"][k] - P_s[k]) > -1e-12)


def _polar_toy(seed: int = 4, K: int = 30):
    """A nonlinear problem: state (angle rad, range m) as random walks, observed in Cartesian
    coordinates (r cos a, r sin a) + noise; the prior is far enough off to need iterations."""
    rng = np.random.default_rng(seed)
    Q = np.diag([0.05**2, 0.2**2])
    R = np.eye(2) * 0.3**2
    truth = np.empty((K, 2))
    truth[0] = [0.3, 10.0]
    for k in range(1, K):
        truth[k] = truth[k - 1] + rng.multivariate_normal(np.zeros(2), Q)
    zs = np.stack([truth[:, 1] * np.cos(truth[:, 0]), truth[:, 1] * np.sin(truth[:, 0])], -1)
    zs = zs + rng.multivariate_normal(np.zeros(2), R, size=K)
    prior = (np.array([0.9, 8.0]), np.diag([0.5**2, 3.0**2]))
    return Q, R, zs, prior


def _h(x):
    return np.array([x[1] * np.cos(x[0]), x[1] * np.sin(x[0])])


def _h_jac(x):
    return np.array([[-x[1] * np.sin(x[0]), np.cos(x[0])], [x[1] * np.cos(x[0]), np.sin(x[0])]])


def _map_cost_gradient(traj, Q, R, zs, prior):
    """Gradient of the batch MAP cost (prior + process + measurement terms) at traj."""
    x0, P0 = prior
    g = np.zeros_like(traj)
    g[0] += np.linalg.solve(P0, traj[0] - x0)
    Qi, Ri = np.linalg.inv(Q), np.linalg.inv(R)
    for k in range(len(zs)):
        g[k] -= _h_jac(traj[k]).T @ Ri @ (zs[k] - _h(traj[k]))
        if k:
            d = Qi @ (traj[k] - traj[k - 1])
            g[k] += d
            g[k - 1] -= d
    return g


def test_filter_about_a_reference_iterates_to_the_batch_map():
    """One pass of the error-state filter linearized about a fixed reference trajectory (mean
    carried relative to it, prediction offset = the nominal transition's miss of the next
    reference point), then RTS, then the smoothed trajectory as the next reference: Gauss-Newton
    on the batch problem. It converges to the MAP (zero gradient), which the first pass (about
    a poor reference) does not reach."""
    from pipe_nav_core.filter.kalman import ErrorStateKF
    from pipe_nav_core.model.measurements import Measurement

    Q, R, zs, (x0, P0) = _polar_toy()
    K = len(zs)
    ref = np.tile(x0, (K, 1))  # a poor first reference: the prior everywhere
    grads = []
    for _ in range(6):
        kf = ErrorStateKF(P0, 0.9999, x0 - ref[0])
        rec = {"P_upd": [], "P_pred": [], "phi": [], "dx": [], "x_upd": []}
        for k in range(K):
            if k:
                kf.predict(np.eye(2), Q, ref[k - 1] - ref[k])
            x_pred, P_pred = kf.x.copy(), kf.P.copy()
            m = Measurement("z", zs[k] - _h(ref[k]), _h_jac(ref[k]), R)
            assert kf.update(m, gate=False) is not None
            for key, v in zip(rec, (kf.P.copy(), P_pred, np.eye(2), kf.x - x_pred, kf.x.copy())):
                rec[key].append(v)
        e, _ = rts(rec["P_upd"], rec["P_pred"], rec["phi"], rec["dx"])
        ref = ref + np.array(rec["x_upd"]) + e
        grads.append(np.abs(_map_cost_gradient(ref, Q, R, zs, (x0, P0))).max())
    assert grads[0] > 1.0  # one linearization about the prior is far from the optimum
    assert grads[-1] < 1e-6 * grads[0]


def test_arc_chainage_is_the_whole_array_arithmetic():
    """The chainage (compiled, step by step) is what the whole-array formulas give, to
    round-off (einsum sums the three products its own way), also across the antimeridian."""
    import numpy as np
    from pipe_nav_core.geo import attitude as att
    from pipe_nav_core.geo import earth
    from pipe_nav_core.smooth import centreline

    rng = np.random.default_rng(3)
    n = 5000
    for lon0 in (0.1, np.pi - 1e-6):
        lat = 0.9 + np.cumsum(rng.normal(0, 1e-8, n))
        lon = lon0 + np.cumsum(np.abs(rng.normal(0, 1e-8, n)))
        lon = (lon + np.pi) % (2 * np.pi) - np.pi
        h = 10 + np.cumsum(rng.normal(0, 1e-3, n))
        q = att.quat_normalize(rng.normal(0, 1, (n, 4)))
        whole = centreline.arc_chainage(lat, lon, h, q)
        rm, rn = earth.radii(lat[1:])
        dlon = np.diff(np.unwrap(lon))
        step = np.stack([dlon * (rn + h[1:]) * np.cos(lat[1:]), np.diff(lat) * (rm + h[1:]),
                         np.diff(h)], axis=1)  # fmt: skip
        along = np.einsum("ij,ij->i", step, att.dcm_from_quat(q[1:])[:, :, 0])
        ref = np.r_[0.0, np.cumsum(along)]
        assert np.abs(whole - ref).max() < 1e-12 * np.abs(along).sum()
        assert np.all(np.isfinite(whole)) and abs(whole[-1]) < 10.0
