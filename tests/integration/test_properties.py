"""Property tests (hypothesis): random damage of the kinds field data has (drops, duplicates,
reorders, NaN, spikes, clock steps, gaps) never gives a traceback, a non-finite output, or a
quality OK whose sigmas do not cover its error."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.app.pipeline import load_log, smooth_bag
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io import read_bag, read_centreline_csv, write_sensor_bag

BAGS = Path(__file__).resolve().parents[2] / "bags"
SETTINGS = settings(max_examples=25, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture,
                                           HealthCheck.too_slow])  # fmt: skip


@pytest.fixture(scope="module")
def short_log():
    """The sample's first 120 s: three markers, a start at rest, the 45 deg bend."""
    from pipe_nav_core.smooth.segments import cut

    log = load_log(BAGS / "sample.mcap")[0]
    return cut(log, -math.inf, log.imu.t[0] + 120.0)


@pytest.fixture(scope="module")
def truth():
    return read_centreline_csv(BAGS / "sample.truth.csv")


damage = st.fixed_dictionaries({
    "drop": st.floats(0.0, 0.05),
    "duplicate": st.integers(0, 20),
    "reorder": st.integers(0, 20),
    "nan": st.integers(0, 10),
    "spikes": st.integers(0, 3),
    "step_s": st.sampled_from([0.0, 0.0, 2.0, 3600.0]),
    "gap_s": st.sampled_from([0.0, 0.0, 0.5, 8.0]),
    "at": st.floats(0.3, 0.8),
    "seed": st.integers(0, 2**16),
})  # fmt: skip


def damaged(log, d):
    """The log with damage ``d`` applied (in this order): a gap and a clock step at fraction
    ``at`` of the run, dropped, duplicated and reordered IMU samples, NaN values, odometer
    and IMU spikes."""
    rng = np.random.default_rng(d["seed"])
    imu, o, m = log.imu, log.odometer, log.mag
    t_at = imu.t[0] + d["at"] * (imu.t[-1] - imu.t[0])

    def keep(t):
        return ~((t > t_at) & (t < t_at + d["gap_s"]))

    def shift(t):
        return np.where(t > t_at + d["gap_s"], t + d["step_s"], t)

    ki, ko, km = keep(imu.t), keep(o.t), keep(m.t)
    ti, g, a = shift(imu.t[ki]), imu.gyro[ki].copy(), imu.accel[ki].copy()
    keep_i = rng.random(len(ti)) >= d["drop"]
    keep_i[0] = keep_i[-1] = True
    ti, g, a = ti[keep_i], g[keep_i], a[keep_i]
    dup = rng.integers(1, len(ti) - 1, d["duplicate"])
    ti, g, a = (
        np.insert(ti, dup, ti[dup]),
        np.insert(g, dup, g[dup], 0),
        np.insert(a, dup, a[dup], 0),
    )
    for i in rng.integers(1, len(ti) - 2, d["reorder"]):
        ti[i], ti[i + 1] = ti[i + 1], ti[i]
    for i in rng.integers(0, len(ti), d["nan"]):
        g[i, rng.integers(0, 3)] = math.nan
    dist, speed = o.distance[ko].copy(), o.speed[ko].copy()
    for i in rng.integers(1, len(dist) - 1, d["spikes"]):
        dist[i] += rng.choice([-5.0, 5.0])
        a[rng.integers(0, len(a))] *= 30.0
    markers = [dataclasses.replace(x, t=float(shift(np.array(x.t)))) for x in log.markers]
    return dataclasses.replace(
        log, imu=dataclasses.replace(imu, t=ti, gyro=g, accel=a),
        odometer=dataclasses.replace(o, t=shift(o.t[ko]), distance=dist, speed=speed),
        mag=dataclasses.replace(m, t=shift(m.t[km]), field=m.field[km]), markers=markers,
    )  # fmt: skip


@SETTINGS
@given(d=damage)
def test_the_reader_keeps_only_finite_time_ordered_samples(short_log, tmp_path, d):
    bag = tmp_path / "d.mcap"
    write_sensor_bag(bag, damaged(short_log, d))
    log, report = read_bag(bag)
    for t in (log.imu.t, log.odometer.t, log.mag.t):
        assert np.all(np.diff(t) > 0)
    assert np.isfinite(log.imu.gyro).all() and np.isfinite(log.imu.accel).all()
    assert np.isfinite(log.odometer.distance).all()
    if d["nan"]:
        assert report.skipped


@SETTINGS
@given(d=damage)
def test_a_damaged_run_is_smoothed_honestly_or_refused(short_log, truth, tmp_path, d):
    bag = tmp_path / "d.mcap"
    write_sensor_bag(bag, damaged(short_log, d))
    csv = tmp_path / "c.csv"
    try:
        result, _ = smooth_bag(bag, Outputs(csv=str(csv)), config=NavConfig())
    except ValueError as exc:  # a refusal: one line naming the bag
        assert str(bag) in str(exc) or "segment" in str(exc)
        assert not csv.exists()
        return
    est, _ = read_centreline_csv(csv)
    assert np.isfinite(est.lat).all() and np.isfinite(est.h).all()
    assert np.isfinite(est.sigma_enu).all()
    p = result.products
    assert np.isfinite(p.strain_pct).all() and np.isfinite(p.sigma_strain_pct).all()
    status = result.summary["quality"]["status"]
    if status == "OK":
        s = score(est, truth[0], datum=truth[1])
        assert s.inside_3sigma >= 0.9, (s, result.summary["quality"])


# found by CI: odometer spikes during the initial rest ended it, and the live filter diverged
ODOMETER_SPIKES_AT_REST = {"drop": 0.0, "duplicate": 0, "reorder": 0, "nan": 8, "step_s": 0.0,
                           "spikes": 2, "gap_s": 0.5, "at": 0.5, "seed": 2}  # fmt: skip


@SETTINGS
@given(d=damage)
@example(d=ODOMETER_SPIKES_AT_REST)
def test_the_live_engine_stays_finite_and_honest(short_log, truth, d):
    """The same damage through the live engine as ekf_node feeds it (replay_log): no exception,
    every estimate finite, and the estimates it publishes inside their sigmas (or it says it
    is lost and publishes nothing after)."""
    from pipe_nav_core.app.replay import estimates_to_trajectory, replay_log

    r = replay_log(damaged(short_log, d), NavConfig())
    traj = estimates_to_trajectory(r.estimates)
    assert np.isfinite(traj.lat).all() and np.isfinite(traj.sigma_enu).all()
    if len(traj.t) > 10 and d["step_s"] == 0.0:
        assert score(traj, truth[0], datum=truth[1]).inside_3sigma >= 0.9
