"""Clock steps and data gaps (gaps.py): found, named, a clock step undone, a gap not hidden."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.config import NavConfig
from pipe_nav_core.gaps import find_holes, remove_clock_steps
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.pipeline import Outputs, load_log, smooth_bag
from pipe_nav_core.sim.faults import clock_step, data_gap

SAMPLE = Path(__file__).resolve().parents[1] / "bags" / "sample.mcap"


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
    the segment before is smoothed forward; the one after, with two markers, too few to check
    a reversed-time smoothing, is left unmapped and named; no row is written across the gap
    or after it; the rows there are as accurate as a clean run's, sigmas covering the error."""
    from pipe_nav_core.evaluation import score

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
    assert [s["how"] for s in result.summary["segments"]] == ["forward", "unmapped"]
    assert any("not mapped (it would be smoothed in reversed time" in r for r in q["reasons"])
    est, _ = read_centreline_csv(csv)
    assert est.t[-1] < t0 + 0.5
    truth, datum = read_centreline_csv(SAMPLE.with_name("sample.truth.csv"))
    s = score(est, truth, datum=datum)
    assert s.max_h < 0.06 and s.max_v < 0.08 and s.inside_3sigma >= 0.95, s
