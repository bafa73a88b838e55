"""Markers surveyed wrong or stamped late (marker_outliers.py): left out and named, and the run
is then the run without them."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.app.pipeline import load_log, smooth_bag
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.sim.faults import marker_late, marker_moved
from pipe_nav_core.types import Marker

SAMPLE = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"


@pytest.fixture(scope="module")
def log():
    return load_log(SAMPLE)[0]


@pytest.fixture(scope="module")
def without(log, tmp_path_factory):
    """The sample smoothed without agm_02: what every case below must equal."""
    d = tmp_path_factory.mktemp("without")
    bag = d / "without.mcap"
    write_sensor_bag(bag, dataclasses.replace(log, markers=[m for m in log.markers
                                                            if m.name != "agm_02"]))  # fmt: skip
    smooth_bag(bag, Outputs(csv=str(d / "c.csv")), config=NavConfig())
    return read_centreline_csv(d / "c.csv")[0]


@pytest.mark.parametrize(
    ("damage", "off_m"),
    [(lambda lg: marker_moved(lg, 2, 20.0), 20.0), (lambda lg: marker_late(lg, 2, 3.0), 5.8)],
    ids=["surveyed 20 m off", "stamped 3 s late"],
)
def test_a_wrong_marker_is_left_out_and_the_run_equals_the_run_without_it(
    log, without, tmp_path: Path, damage, off_m
):
    bag = tmp_path / "bad.mcap"
    write_sensor_bag(bag, damage(log))  # agm_02, the third marker
    csv = tmp_path / "c.csv"
    result, report = smooth_bag(bag, Outputs(csv=str(csv)), config=NavConfig())
    s = result.summary
    assert s["marker_outliers"] == ["agm_02"]
    assert (s["markers_used"], s["markers_rejected"], s["markers_total"]) == (3, 1, 4)
    (w,) = [w for w in report.warnings if w.startswith("marker agm_02 left out")]
    assert abs(float(w.split(": ")[1].split(" m")[0]) - off_m) < 0.3
    assert s["quality"]["status"] == "DEGRADED"
    got = read_centreline_csv(csv)[0]
    np.testing.assert_allclose(got.t, without.t)
    np.testing.assert_allclose(got.lat, without.lat, atol=1e-12)
    np.testing.assert_allclose(got.h, without.h, atol=1e-6)


def test_a_clean_run_keeps_every_marker(log):
    from pipe_nav_core.faults.markers import screening
    from pipe_nav_core.smooth.passes import smooth_log

    cfg = NavConfig(imu_grade="industrial")
    result = smooth_log(log, cfg)
    assert max(screening(result, log, cfg).values()) < 10.0


def test_with_two_markers_a_wrong_one_is_warned_about(log, tmp_path: Path):
    two = dataclasses.replace(log, markers=[log.markers[0], log.markers[-1]])
    az = np.radians(75.0)  # the pipe's azimuth at the receive trap: 25 m (8 %) further along it
    bag = tmp_path / "two.mcap"
    write_sensor_bag(bag, marker_moved(two, 1, 25.0 * np.sin(az), 25.0 * np.cos(az)))
    result, report = smooth_bag(bag, Outputs(), config=NavConfig())
    assert any("odometer scale of" in w and "2 markers cannot tell" in w for w in report.warnings)
    assert result.summary["quality"]["status"] != "OK"


def test_the_suspects_are_the_failing_markers_and_their_neighbours():
    """A 100 km line has a hundred markers: leaving each out in turn would smooth the run a
    hundred times (it did: 100 km took hours). A wrong marker bends the run about itself and
    its neighbours, so those are the suspects, in the given order."""
    from pipe_nav_core.faults.markers import NEIGHBOURS, suspects

    markers = [Marker(f"M{i}", float(10 * i), 0.0, 0.0, 0.0, (0.02, 0.02, 0.02)) for i in range(12)]
    shuffled = markers[6:] + markers[:6]  # passage order decides, not the list's
    screen = {m.name: 1.0 for m in markers} | {"M5": 99.0, "M11": 50.0}
    got = [m.name for m in suspects(shuffled, screen, bound=20.0)]
    want = [f"M{i}" for i in range(5 - NEIGHBOURS, 5 + NEIGHBOURS + 1)] + ["M9", "M10", "M11"]
    assert sorted(got) == sorted(want)
    assert got == [m.name for m in shuffled if m.name in want]
    assert suspects(markers, {m.name: 1.0 for m in markers}, bound=20.0) == []
    few = markers[:4]
    assert suspects(few, {"M0": 99.0}, bound=20.0) == few[:3]


def test_a_late_marker_the_smoother_can_fit_is_still_left_out():
    """On the 3 km tactical line (2.5 Hz smoothing epochs) the run fits a passage stamped 3 s
    late to 2 cm of its survey, paying with 6.5 m elsewhere: the residual does not give it
    away, the filter's covariance inflation at that passage does. It is left out and named,
    and the run keeps to the truth (16 cm) and inside its sigmas (98 % of the samples)."""
    from pipe_nav_core.app.pipeline import smooth_with_imu_model
    from pipe_nav_core.bench.evaluation import score
    from pipe_nav_core.sim import get_scenario, simulate

    scn = get_scenario("field10k").with_length(3000.0)
    run = simulate(scn, seed=0)
    cfg = NavConfig.from_dict(scn.estimator_settings())
    result = smooth_with_imu_model(marker_late(run.log, 2, 3.0), cfg)
    assert result.summary["epoch_rate_hz"] == 2.5
    assert result.summary["marker_outliers"] == ["agm_02"]
    s = score(result.centreline, run.truth)
    assert s.max_h < 0.3 and s.inside_3sigma > 0.95
