"""The odometer's two updates, as the filter applies them: the NHC rows and the speed row,
each a model of its own (with and without the reading errors)."""

import numpy as np
import pytest
from measurement_check import check_jacobian, random_state
from pipe_nav_core.model.measurements import odometer
from pipe_nav_core.model.state import Layout

KW = {"speed": 1.3, "lever_rate": 0.02}


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("update", ["nhc", "odometer"])
def test_odometer_jacobians(seed, update):
    rng = np.random.default_rng(seed)
    lay = Layout("ins")
    s = random_state(rng)
    sigma = {"sigma_nhc": 0.01} if update == "nhc" else {"sigma_speed": 0.01}
    kw = {**KW, "vel_b_offset": rng.normal(0, 0.01, 3), **sigma}

    def model(x, lay, **kw):
        return odometer.velocity(x, lay, update, **kw)

    m = model(s, lay, **kw)
    assert m.name == update
    assert m.residual.shape == ((2,) if update == "nhc" else (1,)) and m.R.shape[0] == len(m.H)
    check_jacobian(lambda x: model(x, lay, **kw).residual, s, lay, m.H)
    # with the epoch duration the reading errors at both ends of the epoch enter (quantization)
    s.odoq = np.array([0.002, -0.001])
    mq = model(s, lay, epoch_s=0.1, **kw)
    check_jacobian(lambda x: model(x, lay, epoch_s=0.1, **kw).residual, s, lay, mq.H)
    # 1 / epoch_s along the bore axis u; across it u's small boresight components
    assert np.abs(mq.H[:, lay.odoq]).max() > (5.0 if update == "odometer" else 0.05)
    assert not np.any(m.H[:, lay.odoq])
    # first-estimate Jacobian: only the attitude column moves with vel_jac
    m2 = model(s, lay, vel_jac=s.vel_n + 0.1, **kw)
    np.testing.assert_array_equal(m2.residual, model(s, lay, **kw).residual)
    np.testing.assert_array_equal(m2.H[:, lay.vel], model(s, lay, **kw).H[:, lay.vel])
    assert not np.allclose(m2.H[:, lay.att], model(s, lay, **kw).H[:, lay.att])
    # a rotation about the vertical of velocity and attitude together is invisible to it
    null = np.zeros(lay.n)
    null[lay.att] = [0.0, 0.0, 1.0]
    null[lay.vel] = np.cross([0.0, 0.0, 1.0], s.vel_n + 0.1)
    np.testing.assert_allclose(m2.H @ null, 0.0, atol=1e-12)


def test_the_two_updates_are_the_rows_of_one_velocity_model():
    """The NHC (rows 1-2) and the speed (row 0) split the one body-velocity model, each with
    its own noise, as the filter applies them (NHC first, the speed unless excluded)."""
    rng = np.random.default_rng(4)
    lay = Layout("ins")
    s = random_state(rng)
    off = rng.normal(0, 0.01, 3)
    n = odometer.velocity(s, lay, "nhc", vel_b_offset=off, sigma_nhc=0.02, **KW)
    v = odometer.velocity(s, lay, "odometer", vel_b_offset=off, sigma_speed=0.03, **KW)
    args = (1.3, off, 0.02, 0.03, 0.02, s.vel_n, 0.0)
    r, H, _ = odometer.velocity_k(s.vector(), lay.index, 0, 3, *args)
    np.testing.assert_array_equal(np.r_[v.residual, n.residual], r)
    np.testing.assert_array_equal(np.r_[v.H, n.H], H)
    np.testing.assert_array_equal(v.R, [[0.03**2]])
    np.testing.assert_array_equal(n.R, np.diag([0.02**2, 0.02**2]))
    assert odometer.KINDS == ("nhc", "odometer") and (n.name, v.name) == odometer.KINDS
