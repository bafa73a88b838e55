"""The compiled building blocks of the filter epoch equal their dense textbook formulas."""

import numpy as np
import pytest
from pipe_nav_core.filter.kalman import chi2_threshold, joseph_in_place, predict_k
from pipe_nav_core.model.process import discretize_k
from pipe_nav_core.model.state import Layout

from pipe_nav_core import jit


def _system(rng: np.random.Generator, layout: Layout) -> tuple[np.ndarray, np.ndarray]:
    """A sparse A with nonzero leading rows (att, vel, pos) as the engine builds, and a Q that
    is diagonal plus a dense position block (DR)."""
    n = layout.n
    A = np.zeros((n, n))
    rows = layout.pos.stop
    mask = rng.random((rows, n)) < 0.4
    A[:rows][mask] = rng.normal(0, 0.1, mask.sum())
    Q = np.diag(rng.random(n) * 1e-3)
    B = rng.normal(size=(3, 3))
    Q[layout.pos, layout.pos] += B @ B.T * 1e-2
    return A, Q


@pytest.mark.parametrize("mode", ["ins", "dr"])
def test_discretize_and_predict_equal_dense_formulas(mode):
    rng = np.random.default_rng(1)
    layout = Layout(mode, gyro_errors=True, accel_errors=True)
    n = layout.n
    A, Q = _system(rng, layout)
    phi, qd = discretize_k(A, Q, layout.index)
    phi_ref = np.eye(n) + A + 0.5 * A @ A
    qd_ref = Q + 0.5 * (A @ Q + Q @ A.T) + A @ Q @ A.T / 3.0
    if layout.odoq is not None:
        i = layout.odoq.start
        phi_ref[i : i + 2] = 0.0
        phi_ref[i, i + 1] = 1.0
    np.testing.assert_allclose(phi, phi_ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(qd, 0.5 * (qd_ref + qd_ref.T), rtol=0, atol=1e-15)
    M = rng.normal(size=(n, n))
    P = M @ M.T
    x = rng.normal(size=n)
    offset = rng.normal(size=n)
    x1, P1 = x.copy(), P.copy()
    predict_k(x1, P1, phi, qd, offset)
    np.testing.assert_allclose(x1, phi @ x + offset, rtol=1e-13, atol=1e-13)
    P_ref = phi @ P @ phi.T + qd
    np.testing.assert_allclose(P1, 0.5 * (P_ref + P_ref.T), rtol=1e-12, atol=1e-12)
    assert np.array_equal(P1, P1.T)


@pytest.mark.parametrize("m", [1, 2, 3])
def test_joseph_in_place_equals_dense_formula_and_gates(m):
    rng = np.random.default_rng(m)
    n = 38
    M = rng.normal(size=(n, n))
    P = M @ M.T + np.eye(n)
    x = rng.normal(size=n)
    H = rng.normal(size=(m, n)) * (rng.random((m, n)) < 0.3)
    H[:, 0] = 1.0
    R = np.diag(rng.random(m) + 0.1)
    z = rng.normal(size=m)
    x_new, P_new, dx = x.copy(), P.copy(), np.full(n, np.nan)
    nis, applied = joseph_in_place(P_new, x_new, H, R, z, np.inf, dx)
    r = z - H @ x
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    IKH = np.eye(n) - K @ H
    P_ref = IKH @ P @ IKH.T + K @ R @ K.T
    assert applied
    np.testing.assert_allclose(nis, r @ np.linalg.solve(S, r), rtol=1e-10)
    np.testing.assert_allclose(dx, K @ r, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(x_new, x + dx)
    np.testing.assert_allclose(P_new, 0.5 * (P_ref + P_ref.T), rtol=1e-9, atol=1e-9)
    assert np.array_equal(P_new, P_new.T)
    # gated (NIS above the gate) or singular (S = 0): nothing changes
    for R_, gate in ((R, nis * 0.5), (np.zeros((m, m)), np.inf)):
        H_ = H if gate < np.inf else np.zeros((m, n))
        x_g, P_g, dx_g = x.copy(), P.copy(), np.full(n, 7.0)
        nis_g, applied_g = joseph_in_place(P_g, x_g, H_, R_, z, gate, dx_g)
        assert not applied_g
        assert np.array_equal(x_g, x) and np.array_equal(P_g, P) and np.all(dx_g == 7.0)
    assert nis_g != nis_g  # nan: S singular


def test_kernels_are_recompiled_when_a_module_they_depend_on_changes(tmp_path, monkeypatch):
    files = {
        "__init__.py": "",
        "a.py": "from .sub import b\nfrom .jit import kernel\n\n@kernel\ndef f(): return b.X\n",
        "jit.py": "",
        "sub/__init__.py": "",
        "sub/b.py": "from .. import consts\nX = consts.Y\n",
        "consts.py": "Y = 1\n",
        "cli.py": "from . import a\n",  # imports the kernels, but no kernel imports it
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text(text)
    monkeypatch.setattr(jit, "_PACKAGE", tmp_path)

    def stamp() -> str:
        jit._package_stamp.cache_clear()
        return jit._package_stamp()

    names = {p.relative_to(tmp_path).as_posix() for p in jit._kernel_sources()}
    assert names == {"__init__.py", "a.py", "jit.py", "sub/__init__.py", "sub/b.py", "consts.py"}
    before = stamp()
    assert stamp() == before  # from the memo beside the package
    (tmp_path / "cli.py").write_text("from . import a\nZ = 2\n")
    assert stamp() == before
    (tmp_path / "consts.py").write_text("Y = 22\n")  # two imports away from the kernel
    assert stamp() != before
    jit._package_stamp.cache_clear()


def test_the_command_line_io_and_simulator_are_outside_the_kernels():
    names = {p.relative_to(jit._PACKAGE).as_posix() for p in jit._kernel_sources()}
    assert {"filter/epoch.py", "model/mechanization.py", "config.py", "smooth/rts.py"} <= names
    assert not names & {
        "app/cli.py",
        "app/pipeline.py",
        "smooth/passes.py",
        "io/bagwrite.py",
        "sim/run.py",
    }


@pytest.mark.parametrize("dof", [1, 2, 3, 6])
def test_gate_is_the_chi_square_quantile(dof):
    from scipy.stats import chi2

    for p in (0.95, 0.999, 0.99999):
        assert chi2_threshold(p, dof) == pytest.approx(chi2.ppf(p, dof), rel=1e-12)
