"""pipe-nav info: what a bag holds, measured before smoothing."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.info import describe_bag, format_info
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io import write_sensor_bag
from pipe_nav_core.model.imu_noise import allan_deviation, static_spans
from pipe_nav_core.model.sensors import GRADES
from pipe_nav_core.sim import simulate
from pipe_nav_core.smooth.logs import slice_log
from pipe_nav_core.types import SensorLog

SAMPLE = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"


def test_sample_bag():
    info = describe_bag(SAMPLE)
    rows = {r["topic"]: r for r in info["topics"]}
    assert rows["/imu/data"]["count"] == 19206 and rows["/imu/data"]["rate_hz"] == pytest.approx(
        100
    )
    assert rows["/odom/wheel"]["rate_hz"] == pytest.approx(50) and rows["/odom/wheel"]["gaps"] == 0
    assert [m["surveyed"] for m in info["markers"]] == [True] * 4
    assert info["static_spans_s"][0][0] == pytest.approx(0.0, abs=0.1)
    assert 295 < info["distance_m"] < 305
    spec = GRADES["industrial"]  # the sample's IMU
    noise = info["imu_noise_measured"]
    np.testing.assert_allclose(noise["gyro_arw"], spec.gyro_arw, rtol=0.15)
    np.testing.assert_allclose(noise["accel_vrw"], spec.accel_vrw, rtol=0.15)
    assert info["imu_grade"]["nearest_to_measured"] == "industrial"
    text = format_info(info)
    assert "consider --imu-grade" not in text and "agm_03" in text


def test_a_consumer_run_with_a_hole_in_its_data(tmp_path):
    run = simulate("drag180", 1)  # consumer MEMS
    log = run.log
    t0 = float(log.imu.t[0])
    a, b = slice_log(log, t0, t0 + 40.0), slice_log(log, t0 + 70.0, float(log.imu.t[-1]) + 1)
    holed = SensorLog(
        imu=type(log.imu)(*(np.concatenate([x, y]) for x, y in zip(
            (a.imu.t, a.imu.gyro, a.imu.accel), (b.imu.t, b.imu.gyro, b.imu.accel), strict=True))),
        odometer=type(log.odometer)(*(np.concatenate([x, y]) for x, y in zip(
            (a.odometer.t, a.odometer.distance, a.odometer.speed),
            (b.odometer.t, b.odometer.distance, b.odometer.speed), strict=True))),
        mag=log.mag,
        markers=log.markers,
    )  # fmt: skip
    bag = tmp_path / "holed.mcap"
    write_sensor_bag(bag, holed)
    info = describe_bag(bag, NavConfig(imu_grade="industrial"))  # a wrong named grade
    imu = next(r for r in info["topics"] if r["topic"] == "/imu/data")
    assert imu["gaps"] == 1 and imu["largest_gap_s"] == pytest.approx(30.0, abs=0.05)
    assert imu["largest_gap_at_s"] == pytest.approx(40.0, abs=0.1)
    assert info["imu_grade"]["nearest_to_measured"] == "consumer"
    text = format_info(info)
    assert "consider --imu-grade consumer" in text and "1 gap(s)" in text
    auto = format_info(describe_bag(bag))  # the default, imu_grade auto
    assert "auto -> consumer" in auto and "fits consumer" in auto


def test_allan_deviation_of_white_noise_falls_as_one_over_root_tau():
    rng = np.random.default_rng(3)
    dt, density = 0.01, 1e-3
    x = rng.normal(0.0, density / math.sqrt(dt), size=(200_000, 1))
    tau, dev = allan_deviation(x, dt)
    np.testing.assert_allclose(dev[:8, 0], density / np.sqrt(tau[:8]), rtol=0.1)


def test_no_odometer_means_one_static_span_over_the_imu():
    run = simulate("demo", 0)
    log = SensorLog(imu=slice_log(run.log, 0, 5 + float(run.log.imu.t[0])).imu)
    (span,) = static_spans(log)
    assert span == (float(log.imu.t[0]), float(log.imu.t[-1]))


def test_cli_json_and_bad_input(tmp_path):
    cmd = [sys.executable, "-m", "pipe_nav_core.app.cli", "info"]
    r = subprocess.run([*cmd, str(SAMPLE), "--json"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)  # strict JSON: no NaN
    assert json.dumps(info, allow_nan=False)
    r = subprocess.run([*cmd, str(tmp_path / "nope.mcap")], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "nope.mcap" in r.stderr


def test_an_imu_on_a_clock_of_its_own(tmp_path):
    """The sample's IMU stamped 3 s early: named, and its noise measured as pipe-nav smooth
    re-times it (else the odometer's rests hold IMU samples of motion: consumer-like noise)."""
    from pipe_nav_core.app.pipeline import load_log
    from pipe_nav_core.sim.faults import imu_clock

    clean = describe_bag(SAMPLE)
    assert (
        abs(clean["imu_clock"]["offset_s"]) < 0.02 and not clean["imu_clock"]["retimed_by_smooth"]
    )
    assert not any(w.startswith("IMU clock") for w in clean["warnings"])
    bag = tmp_path / "early.mcap"
    write_sensor_bag(bag, imu_clock(load_log(SAMPLE, repair=False)[0], -3.0))
    info = describe_bag(bag)
    assert info["imu_clock"]["retimed_by_smooth"] and info["imu_clock"]["events"] == 4
    assert info["imu_clock"]["offset_s"] == pytest.approx(-3.0, abs=0.02)
    assert info["imu_grade"]["nearest_to_measured"] == "industrial"
    text = format_info(info)
    assert "Warning:         IMU clock: its stamps are " in text and " ms earlier than " in text
