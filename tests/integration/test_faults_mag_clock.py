"""A magnetometer stamped on a clock of its own (faults.mag_clock): its offset from the
smoothed attitude measured on the field the pig carries, taken out before the welds are found
and named; a clean run, or one whose pig never turns, left as it is."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.app.pipeline import load_log, smooth_bag, smooth_with_imu_model
from pipe_nav_core.config import NavConfig
from pipe_nav_core.faults import mag_clock
from pipe_nav_core.io import write_sensor_bag
from pipe_nav_core.sim import simulate
from pipe_nav_core.sim.faults import mag_clock as late_mag
from pipe_nav_core.sim.scenarios import get_scenario

BAGS = Path(__file__).resolve().parents[2] / "bags"


@pytest.fixture(scope="module")
def drag():
    """The 180 m drag test (consumer IMU, tight bends, magnetometer 50 Hz), smoothed."""
    scn = get_scenario("drag180")
    run = simulate(scn, seed=1)
    result = smooth_with_imu_model(run.log, NavConfig.from_dict(scn.estimator_settings()))
    return run.log, result.centreline


@pytest.mark.parametrize("offset", [0.1, 0.3, -2.0])
def test_an_offset_is_measured_and_taken_out(drag, offset):
    log, centreline = drag
    damaged = late_mag(log, offset)
    kept = damaged.mag.t.copy()
    back, found = mag_clock.taken_out(damaged, centreline)
    assert found is not None and found.retime
    assert abs(found.seconds - offset) < 0.01 and found.sigma < 0.02
    assert np.max(np.abs(back.mag.t - log.mag.t)) < 0.01
    assert np.array_equal(back.imu.t, log.imu.t)  # the IMU's clock is the reference
    assert np.array_equal(damaged.mag.t, kept)  # the input is not modified
    way = "later" if offset > 0 else "earlier"
    assert f"ms {way} than the IMU's" in found.describe()


def test_a_clean_run_is_left_as_it_is(drag):
    log, centreline = drag
    back, found = mag_clock.taken_out(log, centreline)
    assert found is not None and not found.retime and abs(found.seconds) < 0.015
    assert back is log


def test_a_pig_that_never_turns_moves_nothing():
    """The field line's first 2 km, seed 2: hardly a turn, so the offset is not known (a
    sigma of seconds); the magnetometer is left as it is rather than moved on a guess."""
    scn = get_scenario("field10k").with_length(2000.0)
    run = simulate(scn, seed=2)
    result = smooth_with_imu_model(run.log, NavConfig.from_dict(scn.estimator_settings()))
    found = mag_clock.measure(run.log, result.centreline)
    assert found is not None and not found.retime and found.sigma > 0.5


def test_too_little_field_is_not_measured(drag):
    log, centreline = drag
    few = replace(log, mag=replace(log.mag, t=log.mag.t[:30], field=log.mag.field[:30]))
    assert mag_clock.measure(few, centreline) is None
    short = replace(centreline, **{f: getattr(centreline, f)[:2] for f in ("t", "quat_nb")})
    assert mag_clock.measure(log, short) is None


def test_the_correlations_and_grams_are_the_products_they_stand_for():
    rng = np.random.default_rng(4)
    x, b = rng.normal(size=(70, 10)), rng.normal(size=(50, 3))
    got = mag_clock._correlations(x, b)
    assert got.shape == (21, 10, 3)
    for m in (0, 7, 20):
        assert np.allclose(got[m], x[m : m + 50].T @ b, atol=1e-12)
    lo = np.array([3, 5, 11])
    grams = mag_clock._grams(x, lo, 40)
    for i, a in enumerate(lo):
        assert np.allclose(grams[i], x[a : a + 40].T @ x[a : a + 40], atol=1e-12)
    curve = (np.arange(9) - 5.3) ** 2  # a parabola's minimum, 1.3 steps right of the middle
    assert mag_clock._minimum(curve) == pytest.approx(1.3)


def test_the_smoothed_sample_with_a_late_magnetometer_has_its_welds_in_place(tmp_path):
    """pipe-nav smooth on the sample with its magnetometer 0.3 s late: named, DEGRADED, and
    its welds where the clean run has them, to 8 mm (before: quality OK, 27 welds for 24,
    0.52-0.96 m downstream and three false ones, nearly all at full confidence)."""
    log = load_log(BAGS / "sample.mcap", repair=False)[0]
    bag = tmp_path / "late.mcap"
    write_sensor_bag(bag, late_mag(log, 0.3))
    clean, _ = smooth_bag(BAGS / "sample.mcap", Outputs(), config=NavConfig())
    late, report = smooth_bag(bag, Outputs(), config=NavConfig())
    assert any(w.startswith("magnetometer clock: its stamps are 30") for w in report.warnings)
    assert late.summary["quality"]["status"] == "DEGRADED"  # type: ignore[index]
    assert clean.welds and late.welds and len(late.welds) == len(clean.welds)
    moved = [a.distance - b.distance for a, b in zip(late.welds, clean.welds, strict=True)]
    assert np.max(np.abs(moved)) < 0.03
