"""imu_grade auto: the IMU noise model from the run's own data (pipe_nav_core.model.imu_noise)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pipe_nav_core.app.pipeline import smooth_with_imu_model
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.model import imu_noise as imu_model
from pipe_nav_core.model.sensors import GRADES
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.smooth.passes import smooth_log


@pytest.mark.parametrize("grade", sorted(GRADES))
@pytest.mark.parametrize("name", ["drag180", "sag104", "undulation90", "demo"])
def test_auto_names_the_grade_that_recorded_the_run(name, grade):
    scn = dataclasses.replace(get_scenario(name), imu_grade=grade, imu_spec=None)
    run = simulate(scn, 4)
    choice = imu_model.choose(run.log, NavConfig())
    assert choice.grade == grade and choice.config.imu_grade == grade, choice.reason
    assert "static spans" in choice.reason and not choice.config.imu_overrides


def test_a_named_grade_is_used_as_given():
    run = simulate("drag180", 0)
    choice = imu_model.choose(run.log, NavConfig(imu_grade="industrial"))
    assert choice.config.imu_grade == "industrial" and choice.reason == "given in the settings"


def test_an_imu_between_the_grades_gets_its_measured_noise():
    spec = dataclasses.replace(GRADES["industrial"].scaled(3.0), name="custom")
    run = simulate(dataclasses.replace(get_scenario("sag104"), imu_spec=spec), 0)
    choice = imu_model.choose(run.log, NavConfig())
    assert choice.grade == "consumer+measured", choice.reason
    over = choice.config.imu_overrides
    assert over["gyro_arw"] == pytest.approx(spec.gyro_arw, rel=0.1)
    assert over["accel_vrw"] == pytest.approx(spec.accel_vrw, rel=0.1)


def test_without_a_static_span_the_declared_noise_is_used():
    run = simulate("demo", 0)
    moving = dataclasses.replace(run.log, odometer=dataclasses.replace(
        run.log.odometer, distance=run.log.odometer.distance + np.arange(len(run.log.odometer.t))
    ))  # fmt: skip
    spec, dt = GRADES["tactical"], 1.0 / run.imu_rate_hz
    declared = {"gyro_variance": [spec.gyro_arw**2 / dt] * 3,
                "accel_variance": [spec.accel_vrw**2 / dt] * 3}  # fmt: skip
    choice = imu_model.choose(moving, NavConfig(), declared)
    assert choice.grade == "tactical" and "declared" in choice.reason
    choice = imu_model.choose(moving, NavConfig(), {})
    assert choice.grade == "industrial" and "unmeasured" in choice.reason


def _max_h(result, run) -> float:
    return score(result.centreline, run.truth, datum=run.datum).max_h


@pytest.mark.parametrize("name", ["drag180", "undulation90", "sag104"])
def test_default_settings_smooth_as_well_as_the_right_grade(name):
    run = simulate(name, 1)
    auto = smooth_with_imu_model(run.log, NavConfig())
    given = smooth_log(run.log, NavConfig(imu_grade=run.scenario.imu_grade), iterations=2)
    assert auto.summary["imu_model"]["grade"] == run.scenario.imu_grade
    assert _max_h(auto, run) <= 1.1 * _max_h(given, run)
    assert not auto.summary["warnings"]


def test_a_model_that_does_not_fit_is_refitted_and_said(monkeypatch):
    run = simulate("drag180", 1)  # consumer MEMS
    wrong = imu_model.ImuModelChoice(NavConfig(imu_grade="tactical"), "tactical", "forced")
    monkeypatch.setattr(imu_model, "choose", lambda *a, **k: wrong)
    said: list[str] = []

    class Told:  # a Progress that keeps the stages
        def stage(self, text: str) -> None:
            said.append(text)

        def fraction(self, done: float) -> None:
            pass

    result = smooth_with_imu_model(run.log, NavConfig(), progress=Told())
    model = result.summary["imu_model"]
    assert model["grade"] == "consumer" and "did not fit" in model["reason"]
    assert any("refitted with industrial" in m for m in said)
    assert any("refitted with consumer" in m for m in said)
    assert not result.summary["warnings"] and _max_h(result, run) < 0.3


@pytest.mark.parametrize("name", ["drag180", "sag104"])
def test_the_live_filter_chooses_at_its_initial_rest(name):
    from pipe_nav_core.app.replay import replay_log

    run = simulate(name, 1)
    settings = run.scenario.estimator_settings()
    auto = replay_log(run.log, NavConfig.from_dict({**settings, "imu_grade": "auto"}))
    given = replay_log(run.log, NavConfig.from_dict(settings))
    assert auto.diagnostics["imu_model"] == run.scenario.imu_grade
    assert "initial rest" in str(auto.diagnostics["imu_model_reason"])
    np.testing.assert_array_equal([e.lat for e in auto.estimates], [e.lat for e in given.estimates])


def test_a_short_rest_falls_back_on_the_declared_noise():
    run = simulate("drag180", 0)
    imu = run.log.imu
    n = 50  # 0.5 s of rest: too few samples to measure
    spec, dt = GRADES["consumer"], 1.0 / run.imu_rate_hz
    declared = {"gyro_variance": [spec.gyro_arw**2 / dt] * 3,
                "accel_variance": [spec.accel_vrw**2 / dt] * 3}  # fmt: skip
    args = (imu.t[:n], imu.gyro[:n], imu.accel[:n], NavConfig())
    assert imu_model.choose_at_rest(*args, declared).grade == "consumer"
    assert imu_model.choose_at_rest(*args).grade == "industrial"


def test_the_declared_noise_is_read_from_the_bag_and_used(tmp_path):
    from pipe_nav_core.app.pipeline import load_log
    from pipe_nav_core.io import read_bag, write_sensor_bag
    from pipe_nav_core.io.topics import TopicNames

    run = simulate("demo", 0)
    spec, dt = GRADES["consumer"], 1.0 / run.imu_rate_hz
    gv, av = spec.gyro_arw**2 / dt, spec.accel_vrw**2 / dt
    bag = tmp_path / "declared.mcap"
    write_sensor_bag(bag, run.log, gyro_var=gv, accel_var=av)
    declared = read_bag(bag)[1].imu_noise_declared
    np.testing.assert_allclose(declared["gyro_variance"], [gv] * 3)
    np.testing.assert_allclose(declared["accel_variance"], [av] * 3)
    log, _ = load_log(bag)
    moving = dataclasses.replace(log, odometer=dataclasses.replace(
        log.odometer, distance=log.odometer.distance + np.arange(len(log.odometer.t))
    ))  # fmt: skip
    assert imu_model.choose(moving, NavConfig(), declared).grade == "consumer"
    assert read_bag(bag, TopicNames(imu="/no/such/topic"))[1].imu_noise_declared == {}


def _spans_one_reading_at_a_time(log, min_s):
    """static_spans as defined: every reading a step of the loop (the reference)."""
    d, t, imu_t = log.odometer.distance, log.odometer.t, log.imu.t
    spans, start = [], 0
    for i in range(1, len(t) + 1):
        if i == len(t) or abs(d[i] - d[start]) > imu_model.STILL_M:
            t0 = min(t[start], imu_t[0]) if start == 0 else t[start]
            a, b = max(t0, imu_t[0]), min(t[i - 1], imu_t[-1])
            if b - a >= min_s:
                spans.append((float(a), float(b)))
            start = i
    return spans


@given(
    steps=st.lists(
        st.sampled_from([0.0, 5e-4, 1.5e-3, -1e-3, 3e-3, 0.04, -0.04, math.nan]),
        min_size=2,
        max_size=300,
    ),  # fmt: skip
    dt=st.floats(0.01, 0.3),
    imu_span=st.tuples(st.floats(-2.0, 1.0), st.floats(-1.0, 2.0)),
    min_s=st.sampled_from([0.0, 0.5, 2.0]),
)
@settings(max_examples=300, deadline=None)
def test_static_spans_skip_the_moving_readings_to_the_same_spans(steps, dt, imu_span, min_s):
    """static_spans jumps over the readings that move (each a span of no time): the spans
    are those of the loop over every reading, still ones, creeping ones, gaps (NaN) and all."""
    from types import SimpleNamespace

    t = dt * np.arange(len(steps))
    d = np.cumsum(steps)
    imu_t = np.array([imu_span[0], t[-1] + imu_span[1]])
    log = SimpleNamespace(imu=SimpleNamespace(t=imu_t), odometer=SimpleNamespace(t=t, distance=d))
    assert imu_model.static_spans(log, min_s) == _spans_one_reading_at_a_time(log, min_s)
