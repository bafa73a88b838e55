"""The zero-rate model's Jacobian."""

import numpy as np
import pytest
from measurement_check import MODES, check_jacobian, random_state
from pipe_nav_core.model.measurements import zero_rate
from pipe_nav_core.model.state import Layout


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("mode", MODES)
def test_zero_rate_jacobian(seed, mode):
    rng = np.random.default_rng(seed)
    s = random_state(rng)
    w = rng.normal(0, 1e-3, 3)
    lay = Layout(mode)
    m = zero_rate.zero_rate(s, lay, gyro_mean=w, sigma=1e-4)
    check_jacobian(
        lambda x: zero_rate.zero_rate(x, lay, gyro_mean=w, sigma=1e-4).residual, s, lay, m.H
    )
