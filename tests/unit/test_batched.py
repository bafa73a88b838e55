"""Whole-run operations in batches give the values of doing them at once."""

from __future__ import annotations

import numpy as np
import pytest

from pipe_nav_core import batched


@pytest.mark.parametrize("uniform", [True, False])
@pytest.mark.parametrize("columns", [(), (3,)])
def test_gradient_is_numpys_bit_for_bit(uniform, columns):
    rng = np.random.default_rng(7)
    n = 40
    t = np.arange(n) * 0.005 if uniform else np.cumsum(rng.uniform(0.001, 0.01, n))
    f = np.cumsum(rng.normal(size=(n, *columns)), axis=0)
    ref = np.gradient(f, t, axis=0)
    for batch in (1, 2, 3, 39, 40, 1000):
        assert batched.gradient(f, t, batch).tobytes() == ref.tobytes(), batch
    for m in (2, 3):
        assert (
            batched.gradient(f[:m], t[:m], 1).tobytes()
            == np.gradient(f[:m], t[:m], axis=0).tobytes()
        )
    assert batched.gradient(f[:1], t[:1]).tolist() == np.zeros((1, *columns)).tolist()


def test_row_norms_in_batches_are_numpys():
    """Row norms a few rows at a time (the IMU fault checks at field scale) are
    np.linalg.norm's over the whole, bit for bit, across batch edges and for a last short one."""
    a = np.random.default_rng(4).normal(size=(1000, 3)) * [1e-3, 9.81, 1e4]
    whole = np.linalg.norm(a, axis=1)
    for batch in (1, 7, 999, 1000, 4096):
        assert batched.row_norms(a, batch).tobytes() == whole.tobytes()
    assert batched.row_norms(np.zeros((0, 3))).shape == (0,)
