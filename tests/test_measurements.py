"""Every measurement model's Jacobian matches finite differences of its residual, so that the
filter, the backward filter and the smoothers all linearize the same, correct model."""

import math

import numpy as np
import pytest
from pipe_nav_core.state import Layout, NavState, inject_many
from pipe_nav_core.types import Marker

from pipe_nav_core import attitude as att
from pipe_nav_core import measurements as meas


def _state(rng: np.random.Generator) -> NavState:
    return NavState(
        t=10.0,
        lat=math.radians(31.0),
        lon=math.radians(114.0),
        h=25.0,
        vel_n=rng.normal(0, 1.5, 3),
        q_nb=att.quat_from_euler(rng.uniform(-3, 3), rng.uniform(-0.5, 0.5), rng.uniform(0, 6)),
        bg=rng.normal(0, 1e-3, 3),
        ba=rng.normal(0, 1e-2, 3),
        k=0.01,
        bore=np.array([0.01, -0.02]),
    )


def _check(
    residual, s: NavState, layout: Layout, H: np.ndarray, eps: float = 1e-6, tol: float = 2e-5
) -> None:
    r0 = residual(s)
    num = np.zeros_like(H)
    for j in range(layout.n):
        d = np.zeros(layout.n)
        d[j] = eps
        rp = residual(s.inject(d, layout))
        d[j] = -eps
        rm = residual(s.inject(d, layout))
        num[:, j] = -(rp - rm) / (2 * eps)
    scale = max(1.0, float(np.abs(H).max()))
    np.testing.assert_allclose(H, num, atol=tol * scale, err_msg=f"r0={r0}")


MODES = ["ins", "dr"]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_odometer_velocity_jacobian(seed):
    rng = np.random.default_rng(seed)
    lay = Layout("ins")
    s = _state(rng)
    off = rng.normal(0, 0.01, 3)

    def res(x):
        return meas.odometer_velocity(
            x, lay, speed=1.3, vel_b_offset=off, lever_rate=0.02, sigma_speed=0.01, sigma_nhc=0.01
        ).residual

    m = meas.odometer_velocity(
        s, lay, speed=1.3, vel_b_offset=off, lever_rate=0.02, sigma_speed=0.01, sigma_nhc=0.01
    )
    _check(res, s, lay, m.H)
    # with the epoch duration the reading errors at both ends of the epoch enter (quantization)
    s.odoq = np.array([0.002, -0.001])
    kw = dict(speed=1.3, vel_b_offset=off, lever_rate=0.02, sigma_speed=0.01, sigma_nhc=0.01)
    mq = meas.odometer_velocity(s, lay, epoch_s=0.1, **kw)
    _check(lambda x: meas.odometer_velocity(x, lay, epoch_s=0.1, **kw).residual, s, lay, mq.H)
    assert np.abs(mq.H[:, lay.odoq]).max() > 5.0  # 1 / epoch_s
    # first-estimate Jacobian: only the attitude column moves with vel_jac
    m2 = meas.odometer_velocity(
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


@pytest.mark.parametrize("seed", [0, 1])
def test_zero_velocity_and_rate_jacobians(seed):
    rng = np.random.default_rng(seed)
    lay = Layout("ins")
    s = _state(rng)
    _check(
        lambda x: meas.zero_velocity(x, lay, 0.01).residual,
        s,
        lay,
        meas.zero_velocity(s, lay, 0.01).H,
    )
    w = rng.normal(0, 1e-3, 3)
    for mode in MODES:
        lay = Layout(mode)
        m = meas.zero_rate(s, lay, gyro_mean=w, sigma=1e-4)
        _check(
            lambda x, lay=lay: meas.zero_rate(x, lay, gyro_mean=w, sigma=1e-4).residual, s, lay, m.H
        )


@pytest.mark.parametrize("mode", MODES)
def test_gravity_tilt_jacobian(mode):
    rng = np.random.default_rng(5)
    lay = Layout(mode)
    s = _state(rng)
    f_b = s.c_nb.T @ np.array([0.1, -0.2, 9.8]) + s.ba
    # the kinematic acceleration is laid out with the same attitude (odometer path in DR)
    a_b = s.c_nb.T @ np.array([0.1, -0.2, 0.0])

    def res(x):
        c = x.c_nb
        return meas.gravity_tilt(
            x, lay, f_mean_n=c @ (f_b - x.ba), c_mean=c, accel_n=c @ a_b, sigma=0.01
        ).residual

    c = s.c_nb
    m = meas.gravity_tilt(s, lay, f_mean_n=c @ (f_b - s.ba), c_mean=c, accel_n=c @ a_b, sigma=0.01)
    _check(res, s, lay, m.H)
    # a rotation about the vertical changes nothing the tilt update sees
    assert np.allclose(m.H[2, lay.att], 0.0) and np.allclose(m.H[:, lay.att][:, 2], 0.0)


@pytest.mark.parametrize("mode", MODES)
def test_magnetic_heading_jacobian(mode):
    rng = np.random.default_rng(6)
    lay = Layout(mode)
    s = _state(rng)
    field = rng.normal(0, 3e-5, 3)

    def res(x):
        return meas.magnetic_heading(
            x, lay, field_b=field, c_nb=x.c_nb, declination=0.1, sigma=0.05
        ).residual

    m = meas.magnetic_heading(s, lay, field_b=field, c_nb=s.c_nb, declination=0.1, sigma=0.05)
    _check(res, s, lay, m.H)


@pytest.mark.parametrize("mode", MODES)
def test_marker_fix_jacobian_and_residual(mode):
    rng = np.random.default_rng(7)
    lay = Layout(mode)
    s = _state(rng)
    mk = Marker("agm_01", s.t, s.lat + 1e-6, s.lon - 2e-6, s.h + 0.3, (0.02, 0.02, 0.03))
    m = meas.marker_fix(s, lay, mk, time_sigma=0.03)
    # geodetic-to-ENU linearization: 1e-4 relative (1 mm per 10 m of residual)
    _check(lambda x: meas.marker_fix(x, lay, mk, time_sigma=0.03).residual, s, lay, m.H, tol=1e-4)
    # the residual is the survey minus the estimate in ENU metres
    assert m.residual[1] == pytest.approx(1e-6 * 6.3e6, rel=0.01)
    assert m.residual[2] == pytest.approx(0.3)


@pytest.mark.parametrize("mode", MODES)
def test_flat_state_vector_round_trip_and_batch_injection(mode):
    rng = np.random.default_rng(5)
    layout = Layout(mode, gyro_errors=True, accel_errors=True)
    s = _state(rng)
    s.gm, s.am = rng.normal(0, 1e-3, (3, 3)), rng.normal(0, 1e-3, (3, 3))
    s.odoq = rng.normal(size=2)
    v = s.vector()
    np.testing.assert_array_equal(NavState.from_vector(v).vector(), v)
    dx = rng.normal(0, 1e-2, (5, layout.n))
    many = inject_many(np.stack([v] * 5), dx, layout)
    for row, d in zip(many, dx, strict=True):
        np.testing.assert_allclose(row, s.inject(d, layout).vector(), rtol=0, atol=1e-15)
    assert not np.allclose(many[0], v)  # the corrections did move the state
