"""Clock steps and data gaps (gaps.py): found, named, a clock step undone, a gap not hidden."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.app.pipeline import load_log, smooth_bag
from pipe_nav_core.app.replay import replay_log
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.faults.gaps import fill_holes_at_rest, find_holes, remove_clock_steps
from pipe_nav_core.faults.imu import without_imu_faults
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.sim import simulate
from pipe_nav_core.sim.faults import clock_step, data_gap, imu_dropped, imu_shock
from pipe_nav_core.smooth.logs import reverse_log
from pipe_nav_core.smooth.passes import CONVERGED_RAD, smooth_log
from pipe_nav_core.smooth.segments import _reversed

SAMPLE = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"


@pytest.fixture(scope="module")
def log():
    return load_log(SAMPLE)[0]


@pytest.mark.parametrize("step", [3600.0, 2.5, 0.0])
def test_a_clock_step_is_found_and_undone(log, step):
    stepped = clock_step(log, 100.0, step)
    holes = find_holes(stepped)
    if step == 0.0:
        assert holes == []
        return
    (h,) = holes
    assert h.kind == "clock step" and abs(h.step - step) < 1e-6
    fixed = remove_clock_steps(stepped, holes)
    np.testing.assert_allclose(fixed.imu.t, log.imu.t, atol=1e-6)
    assert [m.t for m in fixed.markers] == pytest.approx([m.t for m in log.markers], abs=1e-6)


def test_a_smoothed_run_with_a_clock_step_equals_the_clean_run(log, tmp_path: Path):
    bag = tmp_path / "step.mcap"
    write_sensor_bag(bag, clock_step(log, 100.0, 3600.0))
    csv, clean_csv = tmp_path / "step.csv", tmp_path / "clean.csv"
    result, report = smooth_bag(bag, Outputs(csv=str(csv)), config=NavConfig())
    clean, _ = smooth_bag(SAMPLE, Outputs(csv=str(clean_csv)), config=NavConfig())
    assert any("clock step of +3600.000 s" in w for w in report.warnings)
    assert result.summary["quality"]["status"] == "DEGRADED"
    a, _ = read_centreline_csv(csv)
    b, _ = read_centreline_csv(clean_csv)
    assert len(a.t) == len(b.t)
    np.testing.assert_allclose(a.t, b.t, atol=1e-6)
    np.testing.assert_allclose(a.lat, b.lat, atol=1e-9)  # 6 mm
    np.testing.assert_allclose(a.h, b.h, atol=0.005)


def test_across_a_data_gap_the_run_is_smoothed_in_segments(log, tmp_path: Path):
    """30 s of every topic lost while the pig moved 58 m (it was 2.1 km off, sigmas 300 m):
    the segment before is smoothed forward, the one after (it ends at rest) in reversed time;
    no row is written across the gap; the rows are as accurate as a clean run's, sigmas
    covering the error."""
    t0 = log.imu.t[0] + 80.0
    damaged = data_gap(log, 80.0, 30.0)
    (h,) = find_holes(damaged)
    assert h.kind == "data gap" and h.moved > 50.0
    bag = tmp_path / "gap.mcap"
    write_sensor_bag(bag, damaged)
    csv = tmp_path / "gap.csv"
    result, _ = smooth_bag(bag, Outputs(csv=str(csv)), config=NavConfig())
    q = result.summary["quality"]
    assert q["status"] == "DEGRADED"
    assert any("data gap of 30.0 s" in r and "not mapped" in r for r in q["reasons"])
    assert [s["how"] for s in result.summary["segments"]] == ["forward", "reversed"]
    assert result.summary["converged"] and not any("did not converge" in r for r in q["reasons"])
    assert result.summary["last_step_rad"] < CONVERGED_RAD  # the least converged segment's
    est, _ = read_centreline_csv(csv)
    assert not np.any((est.t > t0 + 0.5) & (est.t < t0 + 29.5))  # nothing across the gap
    assert est.t[-1] > t0 + 60.0  # the pipe after it is mapped
    truth, datum = read_centreline_csv(SAMPLE.with_name("sample.truth.csv"))
    s = score(est, truth, datum=datum)
    assert s.max_h < 0.06 and s.max_v < 0.08 and s.inside_3sigma >= 0.95, s
    # across the gap: the odometer's bound, and the true pipe inside it
    (b,) = result.summary["bridges"]
    assert b["length"] == pytest.approx(h.moved, rel=0.01)
    assert any("within" in r and "not mapped" in r for r in q["reasons"])
    a = np.array(geodetic_to_enu(b["lat0"], b["lon0"], b["alt0"], *datum_tuple(datum)))
    z = np.array(geodetic_to_enu(b["lat1"], b["lon1"], b["alt1"], *datum_tuple(datum)))
    k = (truth.t > b["t0"]) & (truth.t < b["t1"])
    pts = np.asarray(geodetic_to_enu(truth.lat[k], truth.lon[k], truth.h[k],
                                     *datum_tuple(datum))).reshape(-1, 3)  # fmt: skip
    u = (z - a) / np.linalg.norm(z - a)
    off = np.linalg.norm((pts - a) - np.outer((pts - a) @ u, u), axis=1)
    assert off.max() <= b["within"] < 0.2 * b["length"], (off.max(), b)


@pytest.fixture(scope="module")
def demo():
    """The demo pipe's run and the middle of its stop (s from its first sample)."""
    run = simulate("demo", 2)
    odo = run.log.odometer
    edges = np.flatnonzero(np.diff(np.r_[0, (np.abs(odo.speed) < 1e-6).astype(int), 0]))
    spans = [
        (odo.t[a], odo.t[b - 1])
        for a, b in zip(edges[::2], edges[1::2], strict=True)
        if a > 0 and b < len(odo.t)
    ]  # not the rests at the start and the end
    t0, t1 = max(spans, key=lambda s: s[1] - s[0])
    assert t1 - t0 > 8.0
    return run, float(0.5 * (t0 + t1) - run.log.imu.t[0])


def test_a_shock_while_the_pig_stands_still_is_filled_and_named(demo):
    run, mid = demo
    cfg = NavConfig.from_dict(run.scenario.estimator_settings())
    shocked = imu_shock(run.log, mid - 2.5, 5.0)
    left, faults = without_imu_faults(shocked)
    assert [f.kind for f in faults] == ["shock"]
    filled, holes = fill_holes_at_rest(left)
    assert [h.kind for h in holes] == ["rest"] and "stood still" in holes[0].describe()
    assert not find_holes(filled)  # nothing left for segments
    clean = smooth_log(run.log, cfg)
    fixed = smooth_log(filled, cfg)
    a, b = score(clean.centreline, run.truth), score(fixed.centreline, run.truth)
    assert b.max_h < a.max_h + 0.01 and b.inside_3sigma > 0.99, (a.max_h, b.max_h)
    live = replay_log(shocked, cfg)  # as ekf_node sees it
    assert live.diagnostics.get("state") != "lost"
    assert live.diagnostics["imu_fault_filled_at_rest"] == 1


def test_a_hole_while_the_pig_moves_or_rolls_is_not_filled_at_rest(demo):
    run, mid = demo
    moving = imu_dropped(run.log, mid - 40.0, 5.0)  # 40 s before the stop: under way
    assert fill_holes_at_rest(moving)[1] == []
    still = imu_dropped(run.log, mid - 2.5, 5.0)
    imu = still.imu
    t_end = run.log.imu.t[0] + mid + 2.5
    accel = imu.accel.copy()
    c, s_ = np.cos(0.05), np.sin(0.05)  # rolled 3 deg about x in the hole
    after = imu.t > t_end
    accel[after] = accel[after] @ np.array([[1, 0, 0], [0, c, -s_], [0, s_, c]]).T
    rolled = replace(still, imu=replace(imu, accel=accel))
    assert len(fill_holes_at_rest(still)[1]) == 1
    assert fill_holes_at_rest(rolled)[1] == []


def test_a_run_smoothed_in_reversed_time_is_as_good_as_forward(log):
    """What a segment ending at rest gets: the run in reversed time, aligned at its end, the
    Earth turning backwards (it turned forwards until this session: 1 m off on the 1.2 km demo
    pipe, the initial heading 180 deg off until the second marker)."""
    truth, datum = read_centreline_csv(SAMPLE.with_name("sample.truth.csv"))
    fwd = score(smooth_log(log, NavConfig()).centreline, truth, datum=datum)
    res = smooth_log(reverse_log(log), NavConfig(), reverse=True)
    rev = score(_reversed(res).centreline, truth, datum=datum)
    assert rev.max_h < fwd.max_h + 0.02 and rev.max_v < fwd.max_v + 0.02, (fwd, rev)
    assert rev.inside_3sigma >= 0.95


def datum_tuple(d):
    return (d.lat, d.lon, d.alt)
