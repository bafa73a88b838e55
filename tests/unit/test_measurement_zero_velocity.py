"""The zero-velocity model's Jacobian."""

import numpy as np
import pytest
from measurement_check import check_jacobian, random_state
from pipe_nav_core.model.measurements import zero_velocity
from pipe_nav_core.model.state import Layout


@pytest.mark.parametrize("seed", [0, 1])
def test_zero_velocity_jacobian(seed):
    lay = Layout("ins")
    s = random_state(np.random.default_rng(seed))
    m = zero_velocity.zero_velocity(s, lay, 0.01)
    check_jacobian(lambda x: zero_velocity.zero_velocity(x, lay, 0.01).residual, s, lay, m.H)
