"""One filter pass over a log (smooth.forward.run_forward): fed in time slices, telling its
progress, with the estimates of the whole log at once."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.navigator import Navigator, PassOptions
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.smooth import forward
from pipe_nav_core.smooth.forward import run_forward


class _Fractions:
    """A Progress that keeps the fractions it is told."""

    def __init__(self) -> None:
        self.seen: list[float] = []

    def stage(self, text: str) -> None:
        raise AssertionError(f"a filter pass names no stage ({text})")

    def fraction(self, done: float) -> None:
        self.seen.append(done)


def test_progress_slices_give_identical_results(monkeypatch):
    """A forward pass feeds the log in time slices (and tells the caller's Progress the
    fraction done after each): the estimates are those of the whole log at once."""
    monkeypatch.setattr(forward, "SLICE_MIN_S", 5.0)  # slices of 5 s of data: many
    run = simulate("sag104", seed=6)
    cfg = NavConfig.from_dict(run.scenario.estimator_settings())
    nav = Navigator(cfg, run.log.markers, PassOptions(record=True))
    nav.run(run.log)
    whole = nav.recording
    told = _Fractions()
    sliced = run_forward(run.log, cfg, progress=told).recording
    seen = told.seen
    assert seen[-1] == 1.0 and len(seen) > 10 and seen == sorted(seen)
    np.testing.assert_array_equal(whole.states, sliced.states)
    np.testing.assert_array_equal(
        whole.covariances(np.arange(len(whole))), sliced.covariances(np.arange(len(sliced)))
    )


def test_a_pass_reserves_about_what_it_records():
    """The recording is sized for the pass up front (growing by doubling held the old arrays
    beside new ones twice their size): the counts are a few percent over what is recorded."""
    from pipe_nav_core.smooth.forward import expected_counts

    run = simulate("demo", 0)
    cfg = NavConfig.from_dict(get_scenario("demo").estimator_settings())
    epochs, samples = expected_counts(run.log, cfg)
    rec = run_forward(run.log, cfg).recording
    assert len(rec.states) <= epochs <= 1.05 * len(rec.states)
    assert len(rec.s_t) <= samples <= 1.05 * len(rec.s_t)
    assert len(rec._states._a) == epochs and len(rec._s["t"]._a) == samples  # never grown


def test_non_finite_imu_samples_are_dropped_and_counted():
    """A log's IMU samples with a non-finite stamp or reading are left out of the pass and
    counted (dropped_nan_imu); the pass is that of the log without them, and a clean log
    counts none."""
    run = simulate("sag104", seed=6)
    cfg = NavConfig.from_dict(run.scenario.estimator_settings())
    imu = run.log.imu
    bad = np.array([4000, 4001, 9000])
    keep = np.ones(len(imu), dtype=bool)
    keep[bad] = False
    gyro, accel = imu.gyro.copy(), imu.accel.copy()
    gyro[bad[0], 1], accel[bad[1], 2], gyro[bad[2], 0] = np.nan, np.inf, -np.inf
    damaged = replace(run.log, imu=replace(imu, gyro=gyro, accel=accel))
    clean = replace(run.log, imu=imu.slice(keep))
    a, b = run_forward(damaged, cfg), run_forward(clean, cfg)
    assert a.diagnostics()["dropped_nan_imu"] == 3
    assert b.diagnostics()["dropped_nan_imu"] == 0
    np.testing.assert_array_equal(a.recording.states, b.recording.states)
