"""The marker fix model's Jacobian and residual."""


import numpy as np
import pytest
from measurement_check import MODES, check_jacobian, random_state
from pipe_nav_core.model.measurements import marker
from pipe_nav_core.model.state import Layout
from pipe_nav_core.types import Marker


@pytest.mark.parametrize("mode", MODES)
def test_marker_fix_jacobian_and_residual(mode):
    rng = np.random.default_rng(7)
    lay = Layout(mode)
    s = random_state(rng)
    mk = Marker("agm_01", s.t, s.lat + 1e-6, s.lon - 2e-6, s.h + 0.3, (0.02, 0.02, 0.03))
    m = marker.marker_fix(s, lay, mk, time_sigma=0.03)
    # geodetic-to-ENU linearization: 1e-4 relative (1 mm per 10 m of residual)
    check_jacobian(
        lambda x: marker.marker_fix(x, lay, mk, time_sigma=0.03).residual, s, lay, m.H, tol=1e-4
    )
    # the residual is the survey minus the estimate in ENU metres
    assert m.residual[1] == pytest.approx(1e-6 * 6.3e6, rel=0.01)
    assert m.residual[2] == pytest.approx(0.3)
