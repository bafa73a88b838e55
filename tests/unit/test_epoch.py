"""The compiled epoch's records: every field written where it is read, none overlapping."""

import numpy as np
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter import epoch
from pipe_nav_core.model.sensors import INDUSTRIAL
from pipe_nav_core.model.state import Layout
from pipe_nav_core.records import Fields


def test_fields_are_consecutive_and_sized():
    f = Fields()
    assert (f(), f(3), f(), f.size) == (0, 1, 4, 5)


def test_the_prediction_record_reads_back_every_field_it_keeps():
    """What the prediction keeps (epoch._keep) is what the updates' context reads: distinct
    values in every field, so a field declared shorter than it is written or read (and thus
    overlapping its neighbour) fails; the float record is filled to its last element."""
    rng = np.random.default_rng(3)
    p = epoch.Prediction(
        T=0.1, speed=1.5, lever_rate=0.02, w_yz=0.3, gyro_mean=rng.normal(size=3),
        omega=rng.normal(size=3), mean_vel_b=rng.normal(size=3), f_mean_n=rng.normal(size=3),
        dp=rng.normal(size=3), v_jac=rng.normal(size=3), gyro_slow=rng.normal(size=3), i0=3,
        i1=9, mag_i=5, stopped=True, has_odo=False, excluded=True,
    )  # fmt: skip
    lay = Layout("ins")
    b = epoch.Batch(1, 12, lay.n)
    b.ws[:] = np.nan
    b.ws_i[:] = -7
    epoch._keep.py_func(p, b.ws, b.ws_i)
    assert not np.isnan(b.ws).any() and not (b.ws_i == -7).any()
    dyn = rng.normal(size=epoch.D_SIZE)
    dyn_i = np.array([1, 0, 1], dtype=np.int64)
    assert len(dyn_i) == epoch.D_INT_SIZE
    prm = epoch.parameters(NavConfig(), INDUSTRIAL, np.zeros(3), 1.0, None)
    imu_t = np.arange(12.0)
    q = rng.normal(size=(12, 4))
    c = epoch.context(b.ws, b.ws_i, b.ws_sv, b.ws_m, dyn, dyn_i, lay.index, prm, imu_t, q,
                      np.zeros(0), np.zeros((0, 3)), np.zeros((0, 7)))  # fmt: skip
    assert (c.T, c.speed, c.lever_rate, c.w_yz) == (p.T, p.speed, p.lever_rate, p.w_yz)
    for name in ("gyro_mean", "gyro_slow", "mean_vel_b", "f_mean_n", "dp", "v_jac"):
        np.testing.assert_array_equal(getattr(c, name), getattr(p, name), err_msg=name)
    np.testing.assert_array_equal(b.ws[epoch.W_OMEGA : epoch.W_OMEGA + 3], p.omega)
    assert (c.stopped, c.odo_ok, c.excluded, c.mag_i) == (True, False, True, 5)
    np.testing.assert_array_equal(c.imu_t, imu_t[3:9])
    np.testing.assert_array_equal(c.q, q[3:9])
    assert (c.has_prev_vel, c.free) == (True, False)
    np.testing.assert_array_equal(c.prev_vel, dyn[epoch.D_PREV_VEL : epoch.D_PREV_VEL + 3])
