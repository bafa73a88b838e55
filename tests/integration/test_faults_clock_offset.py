"""An IMU stamped on a clock of its own (faults.clock_offset): its offset from the odometer's
clock, constant or drifting, measured at the pig's starts and stops to some 20 ms and taken
out; clean runs left as they are; what no offset explains named, nothing moved."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.app.pipeline import load_log, smooth_bag
from pipe_nav_core.app.replay import estimates_to_trajectory, replay_log
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.faults import clock_offset
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.sim import simulate
from pipe_nav_core.sim.faults import imu_clock
from pipe_nav_core.sim.scenarios import get_scenario
from pipe_nav_core.smooth.segments import samples_where

BAGS = Path(__file__).resolve().parents[2] / "bags"
EYE = np.eye(3)


@pytest.fixture(scope="module")
def demo():
    """1.5 km of the demo pipe: four starts and stops over 790 s."""
    return simulate(get_scenario("demo").with_length(1500.0), seed=2).log


@pytest.fixture(scope="module")
def sample():
    return load_log(BAGS / "sample.mcap", repair=False)[0]


@pytest.mark.parametrize(("offset", "ppm"), [(0.2, 0.0), (1.5, 0.0), (0.05, 0.0), (0.1, 150.0)])
def test_an_offset_or_a_drift_is_measured_and_taken_out(demo, offset, ppm):
    damaged = imu_clock(demo, offset, ppm)
    found = clock_offset.measure(damaged, EYE)
    assert found is not None and found.retime and not found.irregular
    assert found.events >= 3
    assert (found.rate != 0.0) == (ppm != 0.0)
    back = clock_offset.retimed(damaged, found)
    assert np.max(np.abs(back.imu.t - demo.imu.t)) < 0.02
    assert np.max(np.abs(back.mag.t - demo.mag.t)) < 0.02
    assert np.array_equal(back.odometer.t, demo.odometer.t)  # the odometer's clock is kept
    assert np.array_equal(damaged.imu.t, imu_clock(demo, offset, ppm).imu.t)  # input kept
    way = "later" if ppm == 0.0 else "drift from"
    assert found.describe().startswith(f"IMU clock: its stamps {'are ' if not ppm else ''}")
    assert way in found.describe() and "re-timed to the odometer's clock" in found.describe()


@pytest.mark.parametrize("scenario", ["sag104", "drag180", "undulation90"])
def test_clean_runs_are_left_as_they_are(sample, scenario):
    """The sample and the test pipes (two events each, one of sag104's pitched as the pig set
    off): offsets of at most 20 ms found, none taken out."""
    for log in (sample, simulate(get_scenario(scenario), seed=1).log):
        found = clock_offset.measure(log, EYE)
        assert found is not None and not found.retime and not found.irregular
        assert abs(found.seconds) < 0.02 and found.rate == 0.0


def test_a_single_event_needs_a_gross_offset(sample):
    """The sample's first start alone: 0.1 s is not taken on its word, 0.4 s is."""
    first = samples_where(sample, lambda t: t < sample.imu.t[0] + 40.0)
    assert clock_offset.measure(imu_clock(first, 0.1), EYE).retime is False
    found = clock_offset.measure(imu_clock(first, 0.4), EYE)
    assert found.events == 1 and found.retime and abs(found.seconds - 0.4) < 0.03


def test_a_run_without_a_start_or_stop_is_not_measured(sample):
    t0 = sample.imu.t[0]
    moving = samples_where(sample, lambda t: (t > t0 + 20.0) & (t < t0 + 120.0))
    assert clock_offset.measure(imu_clock(moving, 0.3), EYE) is None


def test_offsets_no_model_explains_are_named_and_nothing_moved(demo):
    """The IMU's clock 0.6 s late over the second half only (the odometer's as recorded)."""
    half = demo.imu.t[0] + 0.5 * (demo.imu.t[-1] - demo.imu.t[0])
    imu = replace(demo.imu, t=np.where(demo.imu.t > half, demo.imu.t + 0.6, demo.imu.t))
    found = clock_offset.measure(replace(demo, imu=imu), EYE)
    assert found is not None and found.irregular and not found.retime
    assert "neither one offset nor a steady drift: not re-timed" in found.describe()


def test_the_smoothed_run_of_a_late_imu_is_as_good_as_the_clean_one(sample, tmp_path):
    """pipe-nav smooth's pipeline on the sample with its IMU 0.2 s late: named, DEGRADED, and
    within a centimetre of the clean run (before, 2.6 m off and a marker falsely left out)."""
    truth = read_centreline_csv(BAGS / "sample.truth.csv")[0]
    errors = []
    for name, log in (("clean", sample), ("late", imu_clock(sample, 0.2))):
        bag, csv = tmp_path / f"{name}.mcap", tmp_path / f"{name}.csv"
        write_sensor_bag(bag, log)
        result, report = smooth_bag(bag, Outputs(csv=str(csv)), config=NavConfig())
        named = [w for w in report.warnings if w.startswith("IMU clock")]
        status = result.summary["quality"]["status"]  # type: ignore[index]
        assert (status, len(named)) == (("OK", 0) if name == "clean" else ("DEGRADED", 1))
        s = score(read_centreline_csv(csv)[0], truth)
        assert s.inside_3sigma >= 0.95
        errors.append(s.max_h)
    assert errors[1] < errors[0] + 0.01, errors


@pytest.mark.parametrize(("late", "state"), [(0.3, "navigating"), (0.6, "lost")])
def test_the_live_engine_re_times_the_imu_at_the_second_marker(sample, late, state):
    """ekf_node's engine (pipe-nav replay) measures the clock on the inputs it keeps until the
    second marker and runs again from the alignment re-timed; an IMU later than its reorder
    window lets it re-time is named and the solution lost, never a confident wrong answer."""
    truth = read_centreline_csv(BAGS / "sample.truth.csv")[0]
    live = replay_log(imu_clock(sample, late), NavConfig())
    assert live.diagnostics["state"] == state
    said = re.match(r"IMU clock: its stamps are (\d+) ms later", str(live.diagnostics["imu_clock"]))
    assert said and abs(int(said[1]) - 1e3 * late) < 30, live.diagnostics["imu_clock"]
    estimates = estimates_to_trajectory(live.estimates)
    assert score(estimates, truth).inside_3sigma >= 0.95
    if state == "lost":
        assert "more than the reorder window" in str(live.diagnostics["lost_reason"])
        assert estimates.t[-1] <= live.diagnostics["lost_since"]
    else:
        assert live.diagnostics["imu_clock_retimed"] == 1
