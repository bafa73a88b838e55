"""The gravity tilt model's Jacobian."""

import numpy as np
import pytest
from measurement_check import MODES, check_jacobian, random_state
from pipe_nav_core.model.measurements import gravity_tilt
from pipe_nav_core.model.state import Layout


@pytest.mark.parametrize("mode", MODES)
def test_gravity_tilt_jacobian(mode):
    rng = np.random.default_rng(5)
    lay = Layout(mode)
    s = random_state(rng)
    f_b = s.c_nb.T @ np.array([0.1, -0.2, 9.8]) + s.ba
    # the kinematic acceleration is laid out with the same attitude (odometer path in DR)
    a_b = s.c_nb.T @ np.array([0.1, -0.2, 0.0])

    def res(x):
        c = x.c_nb
        return gravity_tilt.gravity_tilt(
            x, lay, f_mean_n=c @ (f_b - x.ba), c_mean=c, accel_n=c @ a_b, sigma=0.01
        ).residual

    c = s.c_nb
    m = gravity_tilt.gravity_tilt(
        s, lay, f_mean_n=c @ (f_b - s.ba), c_mean=c, accel_n=c @ a_b, sigma=0.01
    )
    check_jacobian(res, s, lay, m.H)
    # a rotation about the vertical changes nothing the tilt update sees
    assert np.allclose(m.H[2, lay.att], 0.0) and np.allclose(m.H[:, lay.att][:, 2], 0.0)
