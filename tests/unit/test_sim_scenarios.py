"""The named scenarios: what they contain, how long they are, and that they simulate."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pipe_nav_core.bench.evaluation import sag_depth
from pipe_nav_core.config import NavConfig
from pipe_nav_core.model.sensors import imu_grade
from pipe_nav_core.sim import (
    Bend,
    Sag,
    Scenario,
    get_scenario,
    scenario_names,
    simulate,
)
from pipe_nav_core.sim.run import build_motion

NAMES = ["drag180", "sag104", "sag104_deep", "undulation90", "field10k", "field10k_sparse", "demo",
         "bends_test", "strain_span"]  # fmt: skip


def world(name: str, seed: int = 0):
    scn = get_scenario(name)
    return scn, scn.build_geometry(), build_motion(scn, np.random.default_rng(seed))


def min_bend_radius(scn: Scenario) -> float:
    return min(f.radius for f in scn.pipe_features() if isinstance(f, Bend))


def test_names_and_lookup():
    assert scenario_names() == NAMES
    for n in NAMES:
        scn = get_scenario(n)
        assert isinstance(scn, Scenario) and scn.name == n
    with pytest.raises(ValueError, match="unknown scenario 'nope'.*drag180.*demo"):
        get_scenario("nope")


@pytest.mark.parametrize("name", NAMES)
def test_every_scenario_is_consistent(name):
    scn, geometry, motion = world(name)
    assert geometry.length == scn.total_length
    ch = scn.marker_chainage_list()
    assert ch[0] == 0.0 and ch[-1] == pytest.approx(scn.total_length)
    assert np.all(np.diff(ch) > 0)
    # the pig rests in both traps, moves in between and arrives exactly at the end
    assert motion.t_move - motion.t_begin == pytest.approx(scn.static_start)
    assert motion.t_end - motion.t_arrive == pytest.approx(scn.static_end)
    assert motion.chainage(motion.t_arrive)[0] == pytest.approx(scn.total_length, abs=1e-6)
    # realistic bends: at least 1.5 D everywhere
    radii = [f.radius for f in scn.pipe_features() if isinstance(f, Bend)]
    assert not radii or min(radii) >= 1.5 * scn.pipe_diameter - 1e-12
    # honest settings for the estimator are valid and contain no realised error
    settings = scn.estimator_settings()
    cfg = NavConfig.from_dict(settings)
    assert cfg.imu_grade == scn.imu_grade
    assert cfg.pipe_diameter == scn.pipe_diameter
    assert cfg.odometer_lever_arm == (0.0, 0.0, -scn.pipe_diameter / 2)
    assert cfg.mag_declination == scn.mag_declination


def test_drag180():
    scn, geometry, motion = world("drag180")
    assert scn.total_length == 180.0 and scn.pipe_diameter == 0.1
    assert scn.speed == 1.5 and scn.imu_grade == "consumer" and scn.mag_enabled
    assert list(scn.marker_chainage_list()) == [0.0, 180.0]
    assert min_bend_radius(scn) == pytest.approx(0.15)
    pitch = geometry.direction(np.linspace(0, 180, 3601))[1]
    assert 0.5 * math.pi / 180 < np.max(np.abs(pitch)) < 5 * math.pi / 180  # gentle grades
    assert 120.0 < motion.t_arrive - motion.t_move < 140.0


@pytest.mark.parametrize(("name", "depth"), [("sag104", 0.2), ("sag104_deep", 0.415)])
def test_sag104(name, depth):
    scn, geometry, motion = world(name)
    assert scn.total_length == pytest.approx(103.8) and scn.speed == 1.0
    assert scn.imu_grade == "industrial"
    assert list(scn.marker_chainage_list()) == pytest.approx([0.0, 103.8])
    s = np.linspace(0, 103.8, 10_381)
    lat, lon, h = geometry.position(s)
    assert h.min() - scn.alt == pytest.approx(-depth, abs=1e-6)
    assert s[np.argmin(h)] == pytest.approx(50.5, abs=0.05)  # in the middle
    assert 100.0 < motion.t_arrive - motion.t_move < 115.0


def test_undulation90():
    scn, geometry, motion = world("undulation90")
    assert scn.total_length == 90.0 and scn.imu_grade == "consumer"
    assert list(scn.marker_chainage_list()) == [0.0, 90.0]
    h = geometry.position(np.linspace(0, 90, 901))[2]
    assert np.ptp(h) == pytest.approx(2.0, abs=1e-6)
    assert any(isinstance(f, Sag) for f in scn.features)


@pytest.mark.parametrize(("name", "spacing"), [("field10k", 1000.0), ("field10k_sparse", 2500.0)])
def test_field10k(name, spacing):
    scn, geometry, motion = world(name)
    assert scn.total_length == 10_000.0 and scn.pipe_diameter == 0.219
    assert scn.imu_grade == "tactical" and scn.imu_rate_hz == 200.0
    ch = scn.marker_chainage_list()
    np.testing.assert_allclose(np.diff(ch), spacing)
    assert min_bend_radius(scn) >= 3.0 * 0.219 - 1e-12
    n_h = sum(1 for f in scn.pipe_features() if isinstance(f, Bend) and f.plane == "h")
    n_v = sum(1 for f in scn.pipe_features() if isinstance(f, Bend) and f.plane == "v")
    assert n_h >= 5 and n_v >= 20
    duration = motion.t_end - motion.t_begin
    assert 1.35 * 3600 < duration < 1.65 * 3600  # about 1.5 h
    assert 10_000.0 / (motion.t_arrive - motion.t_move) == pytest.approx(1.85, abs=0.1)
    assert len(scn.stops) >= 2
    h = geometry.position(np.linspace(0, 10_000, 2001))[2]
    assert np.ptp(h) > 20.0  # grades follow the terrain


def test_field_variants_share_the_line():
    a, b = get_scenario("field10k"), get_scenario("field10k_sparse")
    s = np.linspace(0, 10_000, 101)
    pa, pb = a.build_geometry().position(s), b.build_geometry().position(s)
    np.testing.assert_array_equal(pa[0], pb[0])
    np.testing.assert_array_equal(pa[2], pb[2])


def test_demo_simulates_with_the_bag_rates():
    run = simulate("demo", seed=0)
    log = run.log
    assert np.median(np.diff(log.imu.t)) == pytest.approx(0.01)
    assert np.median(np.diff(log.odometer.t)) == pytest.approx(0.02)
    assert np.median(np.diff(log.mag.t)) == pytest.approx(0.05)
    assert [m.name for m in log.markers] == ["agm_00", "agm_01", "agm_02", "agm_03"]
    np.testing.assert_allclose(run.marker_chainages, [0, 100, 200, 300])
    assert 150.0 < log.imu.t[-1] - log.imu.t[0] < 210.0  # about 3 minutes
    assert sag_depth(run.truth, start=140.0, end=200.0) == pytest.approx(0.5, abs=1e-3)
    assert run.scenario.imu_grade == "industrial" and len(run.scenario.stops) == 1
    assert np.max(np.abs(log.imu.gyro[:, 0])) > 1.5  # the roll turn


def test_length_override_for_long_runs():
    scn = get_scenario("field10k").with_length(100_000.0)
    assert scn.total_length == 100_000.0
    assert len(scn.marker_chainage_list()) == 101
    motion = build_motion(scn, np.random.default_rng(0))
    assert motion.chainage(motion.t_arrive)[0] == pytest.approx(100_000.0, abs=1e-5)
    assert 13.0 * 3600 < motion.t_end - motion.t_begin < 17.0 * 3600
    # a reduced field run simulates end to end
    short = simulate(get_scenario("field10k").with_length(1200.0), seed=2, imu_rate_hz=50.0)
    assert short.truth.distance[-1] == pytest.approx(1200.0)
    assert [m.name for m in short.log.markers] == ["agm_00", "agm_01"]


def test_explicit_imu_spec_and_validation():
    spec = imu_grade("tactical").scaled(2.0)
    scn = Scenario(name="x", imu_spec=spec)
    assert scn.imu_error_spec() is spec
    assert scn.estimator_settings()["imu_grade"] == "tactical"
    with pytest.raises(ValueError, match="unknown IMU grade"):
        Scenario(name="x", imu_grade="navigation")
    with pytest.raises(ValueError, match="length"):
        Scenario(name="x", length=-1.0)
