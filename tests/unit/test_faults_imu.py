"""IMU shocks, saturation and dropped samples (imu_faults.py, gaps.fill_short_holes): left out
or filled, named, and the centreline still right with sigmas that cover it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.app.pipeline import load_log, smooth_bag
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.faults.gaps import fill_short_holes
from pipe_nav_core.faults.imu import find_imu_faults
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.sim.faults import imu_dropped, imu_pinned, imu_shock

BAGS = Path(__file__).resolve().parents[2] / "bags"


@pytest.fixture(scope="module")
def log():
    return load_log(BAGS / "sample.mcap")[0]


def test_a_clean_imu_has_no_fault(log):
    assert find_imu_faults(log)[1] == []
    assert fill_short_holes(log)[1] == 0


@pytest.mark.parametrize(
    ("damage", "named", "max_h"),
    [
        (lambda lg: imu_shock(lg, 100.0, 5.0), "IMU shock for 4.98 s", 0.06),
        (lambda lg: imu_pinned(lg, 70.0, 0.2), "IMU saturated", 0.15),
        (lambda lg: imu_dropped(lg, 100.0, 0.3), "filled by interpolation", 0.05),
        (lambda lg: imu_dropped(lg, 70.0, 0.95), "data gap of 1.0 s", 0.15),
    ],
    ids=["5 s shock", "0.2 s pinned at 8 g", "0.3 s dropped, steady", "1 s dropped, rolling"],
)
def test_a_damaged_imu_is_named_and_the_centreline_stays_right(log, tmp_path, damage, named,
                                                                max_h):  # fmt: skip
    bag = tmp_path / "bad.mcap"
    write_sensor_bag(bag, damage(log))
    csv = tmp_path / "c.csv"
    result, report = smooth_bag(bag, Outputs(csv=str(csv)), config=NavConfig())
    assert any(named in w for w in report.warnings), report.warnings
    assert result.summary["quality"]["status"] == "DEGRADED"
    est, _ = read_centreline_csv(csv)
    truth, datum = read_centreline_csv(BAGS / "sample.truth.csv")
    s = score(est, truth, datum=datum)
    assert s.max_h < max_h and s.max_v < 0.08 and s.inside_3sigma >= 0.95, s
    assert np.isfinite(est.lat).all() and np.isfinite(est.sigma_enu).all()
