"""The odometer speed and NHC model's Jacobian (with and without the reading errors)."""

import numpy as np
import pytest
from measurement_check import check_jacobian, random_state
from pipe_nav_core.model.measurements import odometer
from pipe_nav_core.model.state import Layout


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_odometer_velocity_jacobian(seed):
    rng = np.random.default_rng(seed)
    lay = Layout("ins")
    s = random_state(rng)
    off = rng.normal(0, 0.01, 3)

    def res(x):
        return odometer.velocity(
            x, lay, speed=1.3, vel_b_offset=off, lever_rate=0.02, sigma_speed=0.01, sigma_nhc=0.01
        ).residual

    m = odometer.velocity(
        s, lay, speed=1.3, vel_b_offset=off, lever_rate=0.02, sigma_speed=0.01, sigma_nhc=0.01
    )
    check_jacobian(res, s, lay, m.H)
    # with the epoch duration the reading errors at both ends of the epoch enter (quantization)
    s.odoq = np.array([0.002, -0.001])
    kw = dict(speed=1.3, vel_b_offset=off, lever_rate=0.02, sigma_speed=0.01, sigma_nhc=0.01)
    mq = odometer.velocity(s, lay, epoch_s=0.1, **kw)
    check_jacobian(lambda x: odometer.velocity(x, lay, epoch_s=0.1, **kw).residual, s, lay, mq.H)
    assert np.abs(mq.H[:, lay.odoq]).max() > 5.0  # 1 / epoch_s
    # first-estimate Jacobian: only the attitude column moves with vel_jac
    m2 = odometer.velocity(
        s,
        lay,
        speed=1.3,
        vel_b_offset=off,
        lever_rate=0.02,
        sigma_speed=0.01,
        sigma_nhc=0.01,
        vel_jac=s.vel_n + 0.1,
    )
    np.testing.assert_array_equal(m2.residual, m.residual)
    np.testing.assert_array_equal(m2.H[:, lay.vel], m.H[:, lay.vel])
    assert not np.allclose(m2.H[:, lay.att], m.H[:, lay.att])
    # a rotation about the vertical of velocity and attitude together is invisible to it
    null = np.zeros(lay.n)
    null[lay.att] = [0.0, 0.0, 1.0]
    null[lay.vel] = np.cross([0.0, 0.0, 1.0], s.vel_n + 0.1)
    np.testing.assert_allclose(m2.H @ null, 0.0, atol=1e-12)
