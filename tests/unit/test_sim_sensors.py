"""Sensor models of the simulator: IMU errors, odometer, magnetometer, markers, reproducibility."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.model.sensors import GRADES, imu_grade
from pipe_nav_core.sim import (
    Bend,
    RollTurn,
    Sag,
    Scenario,
    Stop,
    get_scenario,
    simulate,
)
from pipe_nav_core.sim.imu import ImuErrorModel
from pipe_nav_core.sim.magnetometer import earth_field_enu
from pipe_nav_core.sim.markers import make_markers
from pipe_nav_core.sim.odometer import SlipEpisode, odometer_reading
from pipe_nav_core.sim.run import build_motion

DEG = math.pi / 180.0


def small_scenario(**kw) -> Scenario:
    """About 60 s: a bend, a sag, a stop, a roll turn, industrial IMU, all sensors."""
    d = 0.2
    base = dict(
        name="small",
        lat=47.0 * DEG,
        lon=8.0 * DEG,
        alt=400.0,
        azimuth=120.0 * DEG,
        length=60.0,
        pipe_diameter=d,
        features=(Bend(12.0, -60.0 * DEG, 3 * d, "h"), Sag(25.0, 20.0, 0.3)),
        speed=1.5,
        stops=(Stop(40.0, 3.0),),
        static_start=5.0,
        static_end=5.0,
        roll0=0.2,
        roll_turns=(RollTurn(20.0, 1.0, 2.0),),
        imu_grade="industrial",
        imu_rate_hz=200.0,
        odo_rate_hz=50.0,
        mag_rate_hz=25.0,
        marker_chainages=(0.0, 30.0, 60.0),
    )
    base.update(kw)
    return Scenario(**base)


def error_free(scn: Scenario, **kw) -> Scenario:
    return replace(
        scn,
        imu_spec=imu_grade(scn.imu_grade).scaled(0.0),
        odo_tick=0.0,
        odo_scale_sigma=0.0,
        odo_slip_interval=0.0,
        mag_noise=0.0,
        weld_anomaly=0.0,
        mag_hard_iron=(0.0, 0.0, 0.0),
        marker_time_sigma=0.0,
        survey_sigma_h=0.0,
        survey_sigma_v=0.0,
        **kw,
    )


@pytest.fixture(scope="module")
def run():
    return simulate(small_scenario(), seed=11)


@pytest.fixture(scope="module")
def clean():
    return simulate(error_free(small_scenario()), seed=11)


# -- reproducibility -----------------------------------------------------------------------------
def _same(a, b) -> bool:
    la, lb = a.log, b.log
    return (
        np.array_equal(la.imu.gyro, lb.imu.gyro)
        and np.array_equal(la.imu.accel, lb.imu.accel)
        and np.array_equal(la.odometer.distance, lb.odometer.distance)
        and np.array_equal(la.mag.field, lb.mag.field)
        and la.markers == lb.markers
        and np.array_equal(a.truth.lat, b.truth.lat)
    )


def test_reproducible_from_the_seed_and_independent_of_chunking(run):
    again = simulate(small_scenario(), seed=11)
    assert _same(run, again)
    chunked = simulate(small_scenario(), seed=11, chunk_size=777)
    assert _same(run, chunked)
    other = simulate(small_scenario(), seed=12)
    assert not np.array_equal(run.log.imu.gyro, other.log.imu.gyro)
    assert run.log.markers != other.log.markers
    # the pipe does not depend on the seed
    s = np.linspace(0, 60, 7)
    np.testing.assert_array_equal(run.geometry.position(s)[0], other.geometry.position(s)[0])


def test_truth_decimation_keeps_every_kth_sample(run):
    dec = simulate(small_scenario(), seed=11, truth_every=7)
    np.testing.assert_array_equal(dec.truth.t, run.truth.t[::7])
    np.testing.assert_array_equal(dec.truth.quat_nb, run.truth.quat_nb[::7])
    np.testing.assert_array_equal(dec.log.imu.gyro, run.log.imu.gyro)


# -- log layout ----------------------------------------------------------------------------------
def test_rates_times_and_truth_layout(run):
    log, tr = run.log, run.truth
    assert np.allclose(np.diff(log.imu.t), 1 / 200.0)
    assert np.allclose(np.diff(log.odometer.t), 1 / 50.0)
    assert np.allclose(np.diff(log.mag.t), 1 / 25.0)
    np.testing.assert_array_equal(tr.t, log.imu.t)
    assert tr.quat_nb.shape == (len(tr), 4) and tr.vel_n.shape == (len(tr), 3)
    assert run.datum.lat == tr.lat[0] and run.datum.alt == tr.h[0]
    assert tr.distance[0] == 0.0 and tr.distance[-1] == pytest.approx(60.0, abs=1e-9)
    assert run.imu_noise_variance()[0] == pytest.approx(imu_grade("industrial").gyro_arw ** 2 * 200)


# -- static periods ------------------------------------------------------------------------------
def test_static_periods_are_static(run, clean):
    tr = run.truth
    for sel in (tr.t < run.t_move - 0.1, tr.t > run.t_arrive + 0.1):
        assert np.sum(sel) > 500
        assert np.all(tr.vel_n[sel] == 0.0)
        assert np.ptp(tr.lat[sel]) == 0.0 and np.ptp(tr.h[sel]) == 0.0
        c_nb = att.dcm_from_quat(tr.quat_nb[sel])
        # error-free: exactly the Earth rate projected into the body, and normal gravity
        w_exp = np.einsum("mij,mi->mj", c_nb, earth.earth_rate_n(tr.lat[sel]))
        np.testing.assert_allclose(clean.log.imu.gyro[sel], w_exp, atol=1e-12)
        g = earth.gravity(tr.lat[sel], tr.h[sel])
        np.testing.assert_allclose(np.linalg.norm(clean.log.imu.accel[sel], axis=1), g, atol=1e-9)
        # with errors: the mean matches Earth rate plus the true bias within the noise
        spec = imu_grade("industrial")
        n = np.sum(sel)
        in_period = (run.bias_t >= tr.t[sel][0]) & (run.bias_t <= tr.t[sel][-1])
        bias = np.mean(run.gyro_bias[in_period], axis=0)
        m = run.imu_errors["gyro"].matrix
        expected = np.mean(w_exp, axis=0) @ m.T + bias
        sigma = spec.gyro_arw * math.sqrt(200.0) / math.sqrt(n)
        assert np.all(np.abs(np.mean(run.log.imu.gyro[sel], axis=0) - expected) < 5 * sigma + 1e-7)
        a_norm = np.linalg.norm(np.mean(run.log.imu.accel[sel], axis=0))
        assert abs(a_norm - np.mean(g)) < 5 * spec.accel_turn_on_bias + 0.01


def test_roll_turn_is_present(run):
    roll, _, _ = att.euler_from_dcm(att.dcm_from_quat(run.truth.quat_nb))
    r = np.unwrap(roll)
    assert np.ptp(r) > 2 * math.pi
    assert np.max(run.log.imu.gyro[:, 0]) == pytest.approx(2.0, rel=0.25)  # speed dependent


# -- IMU errors ----------------------------------------------------------------------------------
@pytest.mark.parametrize("grade", sorted(GRADES))
def test_white_noise_and_turn_on_bias_follow_the_grade(grade):
    spec = imu_grade(grade)
    dt = 0.005
    only_white = replace(spec.scaled(0.0), gyro_arw=spec.gyro_arw, accel_vrw=spec.accel_vrw)
    model = ImuErrorModel(only_white, dt, np.random.default_rng(1))
    zero = np.zeros((40_000, 3))
    g, a, _, _ = model.apply(zero, zero)
    np.testing.assert_allclose(g.std(axis=0), spec.gyro_arw / math.sqrt(dt), rtol=0.03)
    np.testing.assert_allclose(a.std(axis=0), spec.accel_vrw / math.sqrt(dt), rtol=0.03)
    # turn-on biases across many runs
    models = [ImuErrorModel(spec, dt, np.random.default_rng(k)) for k in range(600)]
    ons = np.array([m.gyro.errors.turn_on_bias for m in models])
    assert np.std(ons) == pytest.approx(spec.gyro_turn_on_bias, rel=0.1)
    mats = np.array([m.accel.errors.matrix for m in models])
    assert np.std(mats[:, 0, 0] - 1) == pytest.approx(spec.accel_scale_factor, rel=0.15)
    assert np.std(mats[:, 0, 1]) == pytest.approx(spec.accel_misalignment, rel=0.15)


def test_bias_instability_is_gauss_markov_with_the_grade_correlation_time():
    spec = imu_grade("consumer")
    dt = 1.0  # coarse steps: many correlation times quickly
    gm_only = replace(
        spec.scaled(0.0),
        gyro_bias_instability=spec.gyro_bias_instability,
        accel_bias_instability=spec.accel_bias_instability,
    )
    model = ImuErrorModel(gm_only, dt, np.random.default_rng(3))
    zero = np.zeros((200_000, 3))
    g, _, gb, _ = model.apply(zero[:100_000], zero[:100_000])
    g2, _, _, _ = model.apply(zero[100_000:], zero[100_000:])
    b = np.vstack([g, g2])[:, 0]
    assert np.std(b) == pytest.approx(spec.gyro_bias_instability, rel=0.15)
    lag = int(spec.gyro_bias_corr_time / dt)
    rho = np.corrcoef(b[:-lag], b[lag:])[0, 1]
    assert rho == pytest.approx(math.exp(-1.0), abs=0.1)
    np.testing.assert_array_equal(gb, g)  # the reported bias is what was added


def test_quantisation_keeps_the_integral():
    spec = replace(imu_grade("tactical").scaled(0.0), gyro_quantization=1e-4)
    model = ImuErrorModel(spec, 0.01, np.random.default_rng(0))
    x = np.full((1000, 3), 0.0123)
    g, _, _, _ = model.apply(x, x)
    inc = g * 0.01
    np.testing.assert_allclose(inc / 1e-4, np.round(inc / 1e-4), atol=1e-9)
    assert abs(np.sum(inc[:, 0]) - 0.123) <= 1e-4


def test_imu_mounting_rotates_into_imu_link():
    rpy = (0.1, -0.2, 1.0)
    scn = error_free(small_scenario(length=20.0, stops=(), roll_turns=(), marker_chainages=None))
    a = simulate(scn, seed=2)
    b = simulate(replace(scn, imu_mount_rpy=rpy), seed=2)
    back = b.log.to_base_link(b.r_base_imu)
    np.testing.assert_allclose(back.imu.gyro, a.log.imu.gyro, atol=1e-12)
    np.testing.assert_allclose(back.imu.accel, a.log.imu.accel, atol=1e-12)
    np.testing.assert_allclose(back.mag.field, a.log.mag.field, atol=1e-18)
    assert not np.allclose(b.log.imu.accel, a.log.imu.accel)
    assert b.scenario.estimator_settings()["imu_mount_rpy"] == rpy


# -- odometer ------------------------------------------------------------------------------------
def test_error_free_odometer_reads_the_true_wall_distance(clean):
    odo = clean.log.odometer
    np.testing.assert_allclose(odo.distance, clean.wall_distance, rtol=0, atol=1e-12)
    assert odo.distance[0] == 0.0
    # with the wheel at the bottom and a rolling pig, the wall distance differs slightly from
    # the centreline chainage, but not by more than the bend geometry allows
    assert abs(odo.distance[-1] - 60.0) < 0.3 * math.pi / 3 * 0.1 + 1e-3


@pytest.mark.parametrize(("wheel_y", "sign"), [(-0.1, 1.0), (0.1, -1.0), (0.0, 0.0)])
def test_wall_distance_in_a_bend_is_analytic(wheel_y, sign):
    # Left turn of 90 deg, no roll: a wheel on the right wall (outer) reads angle * D / 2 more,
    # on the left wall (inner) that much less, at the bottom the same as the centreline.
    d = 0.2
    scn = error_free(
        small_scenario(
            length=20.0,
            features=(Bend(8.0, -90.0 * DEG, 3 * d, "h"),),
            stops=(),
            roll0=0.0,
            roll_wander=0.0,
            roll_turns=(),
            odo_lever_arm=(0.0, wheel_y, -0.1 if wheel_y == 0.0 else 0.0),
            marker_chainages=None,
        )
    )
    r = simulate(scn, seed=4)
    expected = 20.0 + sign * (math.pi / 2) * (d / 2)
    assert r.log.odometer.distance[-1] == pytest.approx(expected, abs=1e-6)


def test_ticks_scale_and_slips(run):
    odo, scn = run.log.odometer, run.scenario
    tick = scn.odo_tick
    np.testing.assert_allclose(odo.distance / tick, np.round(odo.distance / tick), atol=1e-6)
    assert run.odometer_scale != 0.0
    final = odo.distance[-1]
    ideal = run.wall_distance[-1] * (1 + run.odometer_scale)
    slip_effect = sum(
        e.factor * np.diff(np.interp([e.t_start, e.t_end], odo.t, run.wall_distance))[0]
        for e in run.slips
    )
    assert final == pytest.approx(ideal + slip_effect * (1 + run.odometer_scale), abs=tick + 1e-6)
    # the speed field is a windowed count difference: close to the true speed while cruising
    from pipe_nav_core.sim.kinematics import evaluate

    st = evaluate(run.geometry, run.motion, odo.t)
    cruising = (st.sd > 1.0) & (np.abs(st.sdd) < 0.05)
    err = odo.speed[cruising] - st.sd[cruising]
    assert np.median(np.abs(err)) < tick / scn.odo_speed_window + 0.02


def test_a_stall_stops_the_count():
    t = np.arange(0.0, 10.0, 0.02)
    wall = 1.5 * t
    odo = odometer_reading(
        t, wall, scale_error=0.0, tick=0.0, slips=[SlipEpisode(4.0, 4.5, -1.0)], speed_window=0.1
    )
    inside = (t > 4.0 + 1e-9) & (t <= 4.5 + 1e-9)
    assert np.ptp(odo.distance[inside]) == pytest.approx(0.0, abs=1e-12)
    assert odo.distance[-1] == pytest.approx(wall[-1] - 0.75, abs=1e-9)
    spin = odometer_reading(
        t, wall, scale_error=0.01, tick=0.0, slips=[SlipEpisode(2.0, 3.0, 0.3)], speed_window=0.1
    )
    assert spin.distance[-1] == pytest.approx((wall[-1] + 0.3 * 1.5) * 1.01, abs=1e-9)


def test_default_scenarios_have_brief_frequent_slips():
    r = simulate(get_scenario("demo").with_length(150.0), seed=1)
    assert len(r.slips) >= 1
    assert all(0.0 < e.t_end - e.t_start <= 0.3 + 1e-12 for e in r.slips)
    assert all(-1.0 <= e.factor <= 0.5 for e in r.slips)


# -- magnetometer --------------------------------------------------------------------------------
def test_magnetometer_sees_the_attenuated_earth_field(run, clean):
    scn = run.scenario
    b_n = earth_field_enu(scn.mag_declination, scn.mag_inclination, scn.mag_field)
    from pipe_nav_core.sim.kinematics import evaluate

    st = evaluate(clean.geometry, clean.motion, clean.log.mag.t)
    expected = scn.mag_attenuation * np.einsum("mij,mi->mj", st.c_nb, np.tile(b_n, (len(st.t), 1)))
    np.testing.assert_allclose(clean.log.mag.field, expected, atol=1e-15)
    # with errors: hard iron offset + noise at rest; weld anomalies along the way
    rest = run.log.mag.t < run.t_move
    resid = run.log.mag.field[rest] - expected[rest]
    np.testing.assert_allclose(resid.mean(axis=0), scn.mag_hard_iron, atol=4 * scn.mag_noise / 5)
    assert resid.std(axis=0) == pytest.approx(np.full(3, scn.mag_noise), rel=0.3)
    moving = ~rest
    dev = np.linalg.norm(run.log.mag.field[moving] - expected[moving] - scn.mag_hard_iron, axis=1)
    assert dev.max() > 0.3 * scn.weld_anomaly  # girth welds every ~12 m
    assert np.median(dev) < 3 * scn.mag_noise * math.sqrt(3)


def test_no_magnetometer_gives_an_empty_topic():
    r = simulate(get_scenario("sag104").with_length(20.0), seed=0)
    assert len(r.log.mag) == 0 and r.log.mag.field.shape == (0, 3)


# -- markers -------------------------------------------------------------------------------------
def test_markers_names_chainages_and_times(run, clean):
    ms, true = run.log.markers, run.markers_true
    assert [m.name for m in ms] == ["agm_00", "agm_01", "agm_02"]
    np.testing.assert_allclose(run.marker_chainages, [0.0, 30.0, 60.0])
    assert true[0].t == run.t_move and true[-1].t == run.t_arrive
    s_at = run.motion.chainage(np.array([m.t for m in true]))[0]
    np.testing.assert_allclose(s_at, [0.0, 30.0, 60.0], atol=1e-7)
    lat, lon, h = run.geometry.position(np.array([0.0, 30.0, 60.0]))
    np.testing.assert_allclose([m.lat for m in true], lat, atol=1e-15)
    assert (true[0].lat, true[0].lon, true[0].alt) == (run.datum.lat, run.datum.lon, run.datum.alt)
    for m, tm in zip(ms, true):
        assert m.sigma_enu == (0.02, 0.02, 0.02)
        assert abs(m.t - tm.t) < 5 * 0.02
        enu = earth.geodetic_to_enu(m.lat, m.lon, m.alt, tm.lat, tm.lon, tm.alt)
        assert np.all(np.abs(enu) < 5 * 0.02)
    # the error-free run records the truth exactly
    for m, tm in zip(clean.log.markers, clean.markers_true):
        assert (m.name, m.t) == (tm.name, tm.t)
        assert m.lat == pytest.approx(tm.lat, abs=1e-14)
        assert m.alt == pytest.approx(tm.alt, abs=1e-8)


def test_marker_noise_statistics():
    scn = small_scenario(stops=())
    geometry = scn.build_geometry()
    motion = build_motion(scn, np.random.default_rng(0))
    ch = np.linspace(0.0, 60.0, 3000)
    noisy, true = make_markers(geometry, motion, ch, 0.02, 0.03, 0.05, np.random.default_rng(1), 5)
    dt = np.array([a.t - b.t for a, b in zip(noisy, true)])
    enu = np.array(
        [
            earth.geodetic_to_enu(a.lat, a.lon, a.alt, b.lat, b.lon, b.alt)
            for a, b in zip(noisy, true)
        ]
    )
    assert dt.std() == pytest.approx(0.02, rel=0.06)
    np.testing.assert_allclose(enu.std(axis=0), [0.03, 0.03, 0.05], rtol=0.06)
    assert noisy[5].sigma_enu == (0.03, 0.03, 0.05)


def test_marker_survey_is_one_per_pipe_and_timing_one_per_run():
    scn = small_scenario(stops=())
    geometry = scn.build_geometry()
    motion = build_motion(scn, np.random.default_rng(0))
    ch = np.array([0.0, 20.0, 40.0, 60.0])

    def draw(chainages, run_seed, pipe_seed):
        noisy, true = make_markers(
            geometry,
            motion,
            chainages,
            0.02,
            0.03,
            0.05,
            np.random.default_rng(run_seed),
            pipe_seed,
        )
        d_t = np.array([a.t - b.t for a, b in zip(noisy, true)])
        d_enu = np.array(
            [
                earth.geodetic_to_enu(a.lat, a.lon, a.alt, b.lat, b.lon, b.alt)
                for a, b in zip(noisy, true)
            ]
        )
        return d_t, d_enu

    t1, e1 = draw(ch, 1, 5)
    t2, e2 = draw(ch, 2, 5)
    np.testing.assert_allclose(e1, e2, atol=1e-9)  # one survey for every run
    assert np.all(np.abs(t1 - t2) > 1e-6)  # timing errors are the run's own
    _, e_sub = draw(ch[[1, 3]], 3, 5)  # a sparser marker set on the same pipe
    np.testing.assert_allclose(e_sub, e1[[1, 3]], atol=1e-9)
    _, e_other = draw(ch, 1, 6)  # another pipe, another survey
    assert np.all(np.abs(e_other - e1) > 1e-6)


def test_a_bend_shorter_than_a_sample_turns_the_gyro_and_the_velocity():
    """A 0.25 deg vertical bend of radius 3 D is 5 mm of pipe, passed in 4 ms: the simulated
    IMU's samples integrate it all (the pitch rate to the angle, the specific force to the
    turn of the velocity), as an integrating IMU would; the 5 Lobatto nodes of an interval
    alone missed it, and the true attitude turned by an angle no gyro sample showed."""
    d = 0.2
    angle = 0.25 * DEG

    def clean_run(features):
        scn = error_free(
            small_scenario(
                length=20.0,
                features=features,
                stops=(),
                roll0=0.0,
                roll_wander=0.0,
                roll_turns=(),
                speed=2.0,
                marker_chainages=None,
            )
        )
        return simulate(scn, seed=3)

    bent = clean_run((Bend(10.0, angle, 3 * d, "v"),))
    straight = clean_run(())
    dt = 1.0 / bent.scenario.imu_rate_hz
    # base_link FLU: a pitch up is a negative rate about y; the centripetal impulse is up (z)
    turn = np.sum(bent.log.imu.gyro[:, 1] - straight.log.imu.gyro[:, 1]) * dt
    assert turn == pytest.approx(-angle, rel=1e-3)
    pitch = [np.arcsin(att.dcm_from_quat(r.truth.quat_nb[-1])[2, 0]) for r in (bent, straight)]
    assert pitch[0] - pitch[1] == pytest.approx(angle, rel=1e-6)
    t = bent.log.imu.t
    at = t[np.argmax(np.abs(bent.log.imu.gyro[:, 1] - straight.log.imu.gyro[:, 1]))]
    near = np.abs(t - at) < 0.05  # the bend's samples (after it gravity differs by g angle)
    impulse = np.sum(bent.log.imu.accel[near, 2] - straight.log.imu.accel[near, 2]) * dt
    speed = np.linalg.norm(bent.truth.vel_n[np.searchsorted(bent.truth.t, at)])
    assert impulse == pytest.approx(speed * angle, rel=0.01)
