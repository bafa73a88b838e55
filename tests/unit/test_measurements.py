"""The flat state vector the measurement kernels take, and the measurements' registration."""

import inspect
import re

import numpy as np
import pytest
from measurement_check import MODES, random_state
from pipe_nav_core.filter import epoch
from pipe_nav_core.model import measurements
from pipe_nav_core.model.state import Layout, NavState, inject_many


@pytest.mark.parametrize("mode", MODES)
def test_flat_state_vector_round_trip_and_batch_injection(mode):
    rng = np.random.default_rng(5)
    layout = Layout(mode, gyro_errors=True, accel_errors=True)
    s = random_state(rng)
    s.gm, s.am = rng.normal(0, 1e-3, (3, 3)), rng.normal(0, 1e-3, (3, 3))
    s.odoq = rng.normal(size=2)
    v = s.vector()
    np.testing.assert_array_equal(NavState.from_vector(v).vector(), v)
    dx = rng.normal(0, 1e-2, (5, layout.n))
    many = inject_many(np.stack([v] * 5), dx, layout)
    for row, d in zip(many, dx, strict=True):
        np.testing.assert_allclose(row, s.inject(d, layout).vector(), rtol=0, atol=1e-15)
    assert not np.allclose(many[0], v)  # the corrections did move the state


def test_the_epoch_applies_the_measurements_in_their_order():
    """epoch._updates calls each measurement's apply once, in measurements.ORDER (the order
    the batch solver's factors follow)."""
    src = inspect.getsource(epoch._updates.py_func if hasattr(epoch._updates, "py_func")
                            else epoch._updates)  # fmt: skip
    calls = re.findall(r"^    (\w+)\.apply\(c, x, P, out\)$", src, re.MULTILINE)
    assert calls == [m.__name__.rpartition(".")[2] for m in measurements.ORDER]
