"""A stuck wheel, a spike and a step in the odometer (odometer_faults.py): named, left out, and
the centreline and its chainage as good as without them."""

from __future__ import annotations

from pathlib import Path

import pytest
from pipe_nav_core.config import NavConfig
from pipe_nav_core.evaluation import score
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.odometer_faults import find_odometer_faults, without_faults
from pipe_nav_core.pipeline import Outputs, load_log, smooth_bag
from pipe_nav_core.sim.faults import odometer_spike, odometer_stuck

BAGS = Path(__file__).resolve().parents[1] / "bags"


@pytest.fixture(scope="module")
def log():
    return load_log(BAGS / "sample.mcap")[0]


def test_a_clean_odometer_has_no_fault(log):
    assert find_odometer_faults(log) == []


@pytest.mark.parametrize(
    ("damage", "kind", "named"),
    [
        (lambda lg: odometer_stuck(lg, 90.0, 20.0), "stuck", "odometer stuck for 20.0 s"),
        (lambda lg: odometer_spike(lg, 100.0, 5.0), "spike", "odometer spike of +5.00 m"),
        (lambda lg: odometer_spike(lg, 100.0, -0.5, step=True), "step", "backward step of -0.50 m"),
    ],
    ids=["stuck 20 s", "spike 5 m", "backward step 0.5 m"],
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


def test_a_wheel_stuck_before_the_heading_is_anchored_fails_honestly(log, tmp_path):
    """Stuck for 20 s through the 45 deg bend before the second marker, which anchors the
    heading from the dead-reckoned path: the run cannot be trusted and says so (FAILED, the
    markers disagree with it), and its sigmas still cover its error."""
    bag = tmp_path / "bad.mcap"
    write_sensor_bag(bag, odometer_stuck(log, 40.0, 20.0))
    csv = tmp_path / "c.csv"
    result, _ = smooth_bag(bag, Outputs(csv=str(csv)), config=NavConfig())
    q = result.summary["quality"]
    assert q["status"] == "FAILED" and any("disagree" in r for r in q["reasons"])
    truth, datum = read_centreline_csv(BAGS / "sample.truth.csv")
    assert score(read_centreline_csv(csv)[0], truth, datum=datum).inside_3sigma >= 0.95
