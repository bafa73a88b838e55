"""Pipe geometry on the ellipsoid, smooth profiles and the exact kinematics of the simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pipe_nav_core.bench.evaluation import profile_sag_depth
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.sim import Bend, PipeGeometry, RollTurn, Sag, Scenario, Stop
from pipe_nav_core.sim.kinematics import evaluate
from pipe_nav_core.sim.profiles import RampProfile
from pipe_nav_core.sim.run import build_motion
from scipy.integrate import quad
from scipy.optimize import brentq

DEG = math.pi / 180.0


# -- smooth profiles -----------------------------------------------------------------------------
def test_ramp_profile_integral_and_derivative_are_exact():
    p = RampProfile([1.0, 4.0, 4.5, 9.0], [2.0, 0.5, 1.5, 0.7], [0.0, 2.0, -1.0, 3.0, 0.5], u0=0.0)
    u = np.linspace(-0.5, 12.0, 2001)
    f = p.value(u)
    assert f[0] == 0.0 and f[-1] == 0.5
    # integral against adaptive quadrature of the value
    for x in (0.7, 2.2, 4.25, 5.9, 9.3, 11.5):
        brk = [1, 3, 4, 4.5, 6, 9, 9.7]
        ref = quad(lambda v: float(p.value(v)), 0.0, x, points=brk, limit=200)[0]
        assert p.integral(x) == pytest.approx(ref, abs=1e-9)
    # derivative against central differences; continuity of value and derivative
    e = 1e-6
    fd = (p.value(u + e) - p.value(u - e)) / (2 * e)
    np.testing.assert_allclose(p.deriv(u), fd, atol=1e-5)
    du = u[1] - u[0]
    assert np.max(np.abs(np.diff(f))) < 1.01 * 1.875 * 4.0 / 0.5 * du  # peak slope of a ramp
    assert np.max(np.abs(np.diff(p.deriv(u)))) < 60.0 / 0.5**2 * du
    # inverse of the integral
    target = np.array([0.5, 3.0, 6.0])
    ramp = RampProfile([1.0], [2.0], [0.0, 2.0])
    ti = ramp.invert_integral(target, 0.0, 20.0)
    np.testing.assert_allclose(ramp.integral(ti), target, atol=1e-9)


def test_ramp_profile_rejects_overlaps():
    with pytest.raises(ValueError, match="overlap"):
        RampProfile([0.0, 1.0], [2.0, 1.0], [0.0, 1.0, 2.0])
    with pytest.raises(ValueError):
        RampProfile([0.0], [0.0], [0.0, 1.0])


# -- geodetic integration ------------------------------------------------------------------------
def _meridian_arc(lat0: float, lat1: float) -> float:
    return quad(lambda p: float(earth.radii(p)[0]), lat0, lat1, epsabs=1e-9, epsrel=1e-14)[0]


def test_straight_line_due_north_follows_the_meridian_arc():
    lat0, lon0, length = 45.0 * DEG, 10.0 * DEG, 10_000.0
    g = PipeGeometry(length, lat0, lon0, 0.0, azimuth0=0.0)
    lat, lon, h = g.position(length)
    lat_ref = brentq(lambda x: _meridian_arc(lat0, x) - length, lat0, lat0 + 0.01, xtol=1e-15)
    rm = float(earth.radii(lat_ref)[0])
    assert abs(lat - lat_ref) * rm < 0.01  # within a centimetre (in fact micrometres)
    assert abs(lat - lat_ref) * rm < 1e-4
    assert lon == pytest.approx(lon0, abs=1e-15)
    assert h == pytest.approx(0.0, abs=1e-9)
    # A level pipe is not a straight line in a flat tangent plane: 10 km away it is about
    # L^2 / (2 R) = 7.8 m below the plane of the launch point.
    enu = earth.geodetic_to_enu(lat, lon, h, lat0, lon0, 0.0)
    r_mean = math.sqrt(rm * earth.radii(lat0)[1])
    assert enu[2] == pytest.approx(-(length**2) / (2 * r_mean), abs=0.05)
    assert enu[1] == pytest.approx(length, abs=0.01)


def test_constant_azimuth_east_is_a_parallel():
    lat0, h0, length = 60.0 * DEG, 250.0, 10_000.0
    g = PipeGeometry(length, lat0, 0.3, h0, azimuth0=90.0 * DEG)
    lat, lon, h = g.position(np.array([0.0, length / 2, length]))
    np.testing.assert_allclose(lat, lat0, atol=1e-14)
    rn = float(earth.radii(lat0)[1])
    assert lon[-1] - 0.3 == pytest.approx(length / ((rn + h0) * math.cos(lat0)), rel=1e-12)


def test_bends_turn_by_their_angles_with_the_given_radius():
    d = 0.2
    feats = [
        Bend(10.0, 90.0 * DEG, 1.5 * d, "h"),
        Bend(20.0, -30.0 * DEG, 5.0 * d, "h"),
        Bend(30.0, 10.0 * DEG, 2.0, "v"),
        Bend(40.0, -10.0 * DEG, 2.0, "v"),
    ]
    g = PipeGeometry(60.0, 0.5, 0.5, 10.0, azimuth0=10.0 * DEG, features=feats, diameter=d)
    s = np.linspace(0.0, 60.0, 60_001)
    az, pitch, kh, kv = g.direction(s)
    assert az[s > 19.0][0] == pytest.approx(100.0 * DEG, abs=1e-12)
    assert az[-1] == pytest.approx(70.0 * DEG, abs=1e-12)
    assert pitch[(s > 35.0) & (s < 39.0)] == pytest.approx(10.0 * DEG, abs=1e-12)
    assert pitch[-1] == pytest.approx(0.0, abs=1e-12)
    assert np.max(kh) == pytest.approx(1.0 / (1.5 * d), rel=1e-9)  # tightest curvature = 1/R
    assert np.min(kh) == pytest.approx(-1.0 / (5.0 * d), rel=1e-9)
    np.testing.assert_allclose(np.gradient(az, s), kh, atol=2e-3 / (1.5 * d))
    # position derivative = tangent in ENU
    lat, lon, h = g.position(s[::100])
    enu = earth.geodetic_to_enu(lat, lon, h, g.lat0, g.lon0, g.h0)
    seg = np.linalg.norm(np.diff(enu, axis=0), axis=1)
    assert np.all(seg <= 0.1 + 1e-6) and np.all(seg > 0.1 - 1e-3)  # chords of 0.1 m arcs
    # unsorted input gives the same answer
    idx = np.random.default_rng(0).permutation(len(s))[:500]
    np.testing.assert_allclose(g.direction(s[idx])[0], az[idx], atol=1e-15)


def test_sag_depth_is_exact_and_the_ends_are_level():
    for depth in (0.2, 0.415, 2.0, -0.5):
        g = PipeGeometry(103.8, 0.5, 0.5, 0.0, 0.3, features=[Sag(30.5, 40.0, depth)])
        s = np.linspace(0.0, 103.8, 20_001)
        lat, lon, h = g.position(s)
        pts = earth.geodetic_to_enu(lat, lon, h, g.lat0, g.lon0, g.h0)
        pts[:, 2] = h
        extreme = -h.min() if depth > 0 else h.max()
        assert extreme == pytest.approx(abs(depth), abs=1e-7)
        if depth > 0:
            assert profile_sag_depth(pts) == pytest.approx(depth, abs=1e-6)
            assert s[np.argmin(h)] == pytest.approx(50.5, abs=0.01)
        assert h[-1] == pytest.approx(0.0, abs=1e-9)
        assert g.direction(103.8)[1] == pytest.approx(0.0, abs=1e-12)


def test_vertical_pipes_are_rejected():
    with pytest.raises(ValueError, match="pitch"):
        PipeGeometry(50.0, 0.5, 0.5, 0.0, 0.0, features=[Bend(5.0, 88.0 * DEG, 1.0, "v")])


# -- exact kinematics ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def world():
    d = 0.2
    scn = Scenario(
        name="kin",
        length=40.0,
        pipe_diameter=d,
        features=(
            Bend(8.0, 60.0 * DEG, 3 * d, "h"),
            Bend(12.0, 8.0 * DEG, 1.0, "v"),
            Sag(20.0, 15.0, 0.3),
        ),
        speed=1.2,
        static_start=2.0,
        static_end=2.0,
        roll_turns=(RollTurn(14.0, -1.0, 2.0),),
        stops=(Stop(30.0, 2.0),),
    )
    return scn.build_geometry(), build_motion(scn, np.random.default_rng(5))


def test_state_derivatives_match_finite_differences(world):
    geometry, motion = world
    t = np.linspace(motion.t_begin + 0.5, motion.t_end - 0.5, 400)
    e = 1e-5
    st = evaluate(geometry, motion, t)
    lo = evaluate(geometry, motion, t - e)
    hi = evaluate(geometry, motion, t + e)
    # positions: a larger step (latitude's float64 resolution) with a 4th-order stencil
    e_pos = 1e-3
    p = [evaluate(geometry, motion, t + k * e_pos) for k in (-2, -1, 1, 2)]

    def d_dt(name: str) -> np.ndarray:
        f = [getattr(x, name) for x in p]
        return (f[0] - 8 * f[1] + 8 * f[2] - f[3]) / (12 * e_pos)

    # attitude: dC/dt = C [w_nb x]
    c_dot = (hi.c_nb - lo.c_nb) / (2 * e)
    np.testing.assert_allclose(c_dot, st.c_nb @ att.skew(st.w_nb_b), atol=2e-5)
    # velocity components and their derivative
    np.testing.assert_allclose((hi.v_n - lo.v_n) / (2 * e), st.a_n, atol=2e-5)
    rm, rn = earth.radii(st.lat)
    np.testing.assert_allclose(d_dt("lat") * (rm + st.h), st.v_n[:, 1], atol=1e-5)
    np.testing.assert_allclose(d_dt("lon") * (rn + st.h) * np.cos(st.lat), st.v_n[:, 0], atol=1e-5)
    np.testing.assert_allclose(d_dt("h"), st.v_n[:, 2], atol=1e-5)
    # body frame: x along the velocity, no lateral or vertical body velocity
    v_b = np.einsum("mij,mi->mj", st.c_nb, st.v_n)
    np.testing.assert_allclose(v_b[:, 1:], 0.0, atol=1e-12)
    np.testing.assert_allclose(v_b[:, 0], st.sd, atol=1e-12)
    # the closed-form quaternion is the DCM's
    np.testing.assert_allclose(att.dcm_from_quat(st.quat_nb()), st.c_nb, atol=1e-12)


def test_motion_is_smooth_and_ends_at_rest_at_the_pipe_end(world):
    geometry, motion = world
    t = np.linspace(motion.t_begin, motion.t_end, 20_001)
    s, sd, sdd = motion.chainage(t)
    assert s[0] == 0.0 and s[-1] == pytest.approx(geometry.length, abs=1e-9)
    assert np.all(np.diff(s) >= -1e-12)
    assert np.all(sd >= -1e-12)
    assert np.max(np.abs(np.diff(sd))) < 0.01 and np.max(np.abs(np.diff(sdd))) < 0.05
    assert motion.time_at_chainage(0.0) == motion.t_move
    assert motion.time_at_chainage(geometry.length) == motion.t_arrive
    tm = motion.time_at_chainage(np.array([5.0, 22.5]))
    np.testing.assert_allclose(motion.chainage(tm)[0], [5.0, 22.5], atol=1e-9)
    # the stop at 30 m lasts 2 s
    resting = (sd == 0.0) & (t > motion.t_move) & (t < motion.t_arrive)
    assert np.sum(resting) * (t[1] - t[0]) == pytest.approx(2.0, abs=2 * (t[1] - t[0]))
    assert s[resting] == pytest.approx(30.0, abs=1e-9)
