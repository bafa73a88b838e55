"""The section direction: its Jacobian, the angles its rows measure, and its restart at the
start of each straight section."""

import math

import numpy as np
import pytest
from measurement_check import MODES, check_jacobian, random_state
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.epoch import parameters
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.model.measurements import section_direction as sd
from pipe_nav_core.model.sensors import imu_grade
from pipe_nav_core.model.state import SV_DIR, Layout, layout_for


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("rows", [(True, True), (True, False), (False, True)])
def test_section_direction_jacobian(seed, mode, rows):
    rng = np.random.default_rng(seed)
    s = random_state(rng)
    s.dir = np.array([rng.uniform(-3.0, 3.0), rng.uniform(-0.5, 0.5)])
    lay = Layout(mode, section_direction=True)
    L = lay.index
    r, H, R = sd.section_direction_k(s.vector(), L, *rows, 2e-3)
    assert r.shape == (sum(rows),) and np.allclose(R, np.eye(sum(rows)) * 4e-6)

    def residual(x):
        return sd.section_direction_k(x.vector(), L, *rows, 2e-3)[0]

    check_jacobian(residual, s, lay, H)


@pytest.mark.parametrize("roll", [0.0, 1.0, -2.5])
def test_rows_are_the_axis_angles_from_the_sections_whatever_the_roll(roll):
    """An axis 3 mrad right of and 2 mrad above its section's direction has the residuals
    -3 and -2 mrad (measurement zero minus the model), across the azimuth's wrap too."""
    s = random_state(np.random.default_rng(0))
    s.bore = np.zeros(2)
    for azimuth in (0.4, math.pi - 1e-3):
        s.q_nb = att.quat_from_euler(roll, 0.1, azimuth)
        s.dir = np.array([azimuth - 3e-3, 0.1 - 2e-3])
        r, _, _ = sd.section_direction_k(s.vector(), Layout("ins", section_direction=True).index,
                                         True, True, 1e-3)  # fmt: skip
        assert r == pytest.approx([-3e-3, -2e-3], abs=1e-12)


def test_a_pig_rolling_about_the_pipe_with_its_imu_askew_keeps_its_direction():
    """The rows measure the direction of travel (the odometer's axis u(boresight)), not
    base_link x: a pig whose IMU sits 4 mrad askew rolls about the pipe's axis, base_link x
    cones about it by the boresight, and the residual stays zero at every roll."""
    s = random_state(np.random.default_rng(1))
    s.bore = np.array([4e-3, -3e-3])
    q0 = att.quat_from_euler(0.3, 0.1, 0.4)
    u = np.array([1.0, *s.bore]) / math.hypot(1.0, *s.bore)
    t0 = att.dcm_from_quat(q0) @ u
    s.dir = np.array([math.atan2(t0[0], t0[1]), math.atan2(t0[2], math.hypot(t0[0], t0[1]))])
    lay = Layout("ins", section_direction=True)
    azimuths = []
    for roll in np.linspace(0.0, 2.0 * math.pi, 9):
        s.q_nb = np.asarray(att.qmul(att.qrotvec(*(roll * t0)), tuple(q0)))
        c = att.dcm_from_quat(s.q_nb)
        assert c @ u == pytest.approx(t0, abs=1e-12)
        azimuths.append(math.atan2(c[0, 0], c[1, 0]))
        r, _, _ = sd.section_direction_k(s.vector(), lay.index, True, True, 1e-3)
        assert r == pytest.approx([0.0, 0.0], abs=1e-12)
    assert np.ptp(azimuths) > 6e-3  # base_link x's azimuth swings by twice the boresight


def test_restart_only_where_a_section_starts():
    cfg = NavConfig()
    plan = np.array([[0.0, 20.0], [40.0, 90.0]])
    level = np.array([[10.0, 90.0]])
    prm = parameters(cfg, imu_grade("consumer"), np.zeros(3), 1.0, None, (plan, level))
    lay = Layout("ins", section_direction=True)
    s = random_state(np.random.default_rng(3))
    s.q_nb, s.bore = att.quat_from_euler(0.2, 0.05, 1.2), np.zeros(2)
    d = lay.dir.start
    for d0, d1, restarted in (
        (5.0, 5.1, ()),  # inside both
        (39.95, 40.05, (0,)),  # into the second plan section
        (9.95, 10.05, (1,)),  # into the level one
        (20.0, 20.1, ()),  # out of a section
        (30.0, 30.1, ()),  # between sections
    ):
        phi, qd = np.eye(lay.n) * 2.0, np.full((lay.n, lay.n), 0.5)
        sv = s.vector()
        sd.restart_k(prm, lay.index, d0, d1, sv, phi, qd)
        for r in (0, 1):
            if r in restarted:
                assert not phi[d + r].any() and qd[d + r, d + r] == sd.RESTART_SIGMA**2
                assert np.count_nonzero(qd[d + r]) == 1 and np.count_nonzero(qd[:, d + r]) == 1
                assert sv[SV_DIR][r] == pytest.approx((1.2, 0.05)[r], abs=1e-12)
            else:
                assert phi[d + r, d + r] == 2.0 and sv[SV_DIR][r] == s.dir[r]


def test_the_layout_has_the_state_where_the_gyro_walks_more_than_the_section():
    """Only where straight_pipe_wander is set and the gyro's angle random walk is at least a
    tenth of it per sqrt(s) at 1 m/s: the consumer grade's 1.7e-4 rad/sqrt(s) against 3e-4
    rad/sqrt(m) by default; not the industrial grade's 2.6e-5 nor the tactical 1.2e-5."""
    assert Layout("ins").dir is None
    for grade, wander, has in (
        ("consumer", 3e-4, True),
        ("consumer", 0.0, False),
        ("industrial", 3e-4, False),
        ("industrial", 2e-4, True),
        ("tactical", 3e-4, False),
    ):
        cfg = NavConfig.from_dict({"imu_grade": grade, "straight_pipe_wander": wander})
        lay = layout_for(cfg)
        assert (lay.dir is not None) == has, (grade, wander)
        if has:
            assert lay.n == Layout("ins", True, True).n + 2 and lay.dir.stop == lay.n
