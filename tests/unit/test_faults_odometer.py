"""A stuck wheel, a spike and a step in the odometer (odometer_faults.py): named, left out, and
the centreline and its chainage as good as without them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.app.pipeline import load_log, smooth_bag
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.faults.odometer import find_odometer_faults, without_faults
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.sim import simulate
from pipe_nav_core.sim.faults import odometer_spike, odometer_stuck

BAGS = Path(__file__).resolve().parents[2] / "bags"


@pytest.fixture(scope="module")
def log():
    return load_log(BAGS / "sample.mcap")[0]


def test_a_clean_odometer_has_no_fault(log):
    assert find_odometer_faults(log) == []


@pytest.mark.parametrize(
    ("damage", "kind", "named"),
    [
        (lambda lg: odometer_stuck(lg, 90.0, 20.0), "stuck", "odometer stuck for 20.0 s"),
        # through the 45 deg bend before the second marker, which anchors the heading from
        # the dead-reckoned path (bridged at the speed either side for it)
        (lambda lg: odometer_stuck(lg, 40.0, 20.0), "stuck", "odometer stuck for 20.0 s"),
        (lambda lg: odometer_spike(lg, 100.0, 5.0), "spike", "odometer spike of +5.00 m"),
        (lambda lg: odometer_spike(lg, 100.0, -0.5, step=True), "step", "backward step of -0.50 m"),
    ],
    ids=["stuck 20 s", "stuck 20 s before the anchoring", "spike 5 m", "backward step 0.5 m"],
)
def test_a_wheel_fault_is_named_and_does_not_spoil_the_run(log, tmp_path, damage, kind, named):
    damaged = damage(log)
    (fault,) = without_faults(damaged, find_odometer_faults(damaged))[1]
    assert fault.kind == kind
    bag = tmp_path / "bad.mcap"
    write_sensor_bag(bag, damaged)
    csv = tmp_path / "c.csv"
    result, report = smooth_bag(bag, Outputs(csv=str(csv)), config=NavConfig())
    assert any(named in w for w in report.warnings), report.warnings
    assert result.summary["quality"]["status"] == "DEGRADED"
    est, _ = read_centreline_csv(csv)
    truth, datum = read_centreline_csv(BAGS / "sample.truth.csv")
    s = score(est, truth, datum=datum)
    assert s.max_h < 0.08 and s.max_v < 0.05, s
    assert s.inside_3sigma >= 0.95
    # the chainage is the smoothed path's: nothing lost to the wheel
    assert abs(est.distance[-1] - truth.distance[-1]) < 0.1


def test_a_step_while_the_pig_stands_still_is_a_step_not_a_stuck_wheel():
    """A backward step of the count during a stop (the 3 km field line's case): the stop
    after the one-reading jump is the pig's, not a wheel stuck at the speed of the jump."""
    run = simulate("demo", 2)
    odo = run.log.odometer
    still = np.flatnonzero(np.abs(odo.speed) < 1e-6)
    at = float(odo.t[still[(odo.t[still] > 120.0) & (odo.t[still] < 170.0)][5]] - odo.t[0])
    damaged = odometer_spike(run.log, at, -0.5, step=True)
    (fault,) = without_faults(damaged, find_odometer_faults(damaged))[1]
    assert fault.kind == "step" and fault.size == pytest.approx(-0.5, abs=0.05)
    assert "backward step" in fault.describe() and fault.dropped == 0


def test_dead_reckoning_bridges_an_odometer_hole_at_the_speed_either_side():
    from pipe_nav_core.faults.odometer import bridged_for_dead_reckoning
    from pipe_nav_core.types import OdometerSamples, SensorLog

    t = np.arange(0.0, 30.0, 0.02)
    d = 1.5 * t
    keep = (t < 10.0) | (t > 15.0)  # 5 s left out; the count after it is 7.5 m short
    d_read = np.where(t > 15.0, d - 7.5, d)
    log = SensorLog(odometer=OdometerSamples(t[keep], d_read[keep], np.full(keep.sum(), 1.5)))
    out = bridged_for_dead_reckoning(log).odometer
    assert np.all(np.diff(out.t) > 0) and abs(len(out.t) - len(t)) <= 1
    assert np.allclose(np.interp(t, out.t, out.distance), d, atol=1e-6)  # as if it turned on
    whole = SensorLog(odometer=OdometerSamples(t, d, np.full(len(t), 1.5)))
    assert bridged_for_dead_reckoning(whole) is whole  # nothing to bridge
