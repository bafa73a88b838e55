"""The magnetic heading model's Jacobian."""

import numpy as np
import pytest
from measurement_check import MODES, check_jacobian, random_state
from pipe_nav_core.model.measurements import magnetic_heading
from pipe_nav_core.model.state import Layout


@pytest.mark.parametrize("mode", MODES)
def test_magnetic_heading_jacobian(mode):
    rng = np.random.default_rng(6)
    lay = Layout(mode)
    s = random_state(rng)
    field = rng.normal(0, 3e-5, 3)

    def res(x):
        return magnetic_heading.magnetic_heading(
            x, lay, field_b=field, c_nb=x.c_nb, declination=0.1, sigma=0.05
        ).residual

    m = magnetic_heading.magnetic_heading(
        s, lay, field_b=field, c_nb=s.c_nb, declination=0.1, sigma=0.05
    )
    check_jacobian(res, s, lay, m.H)
