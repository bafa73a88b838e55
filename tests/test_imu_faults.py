"""IMU shocks, saturation and dropped samples (imu_faults.py, gaps.fill_short_holes): left out
or filled, named, and the centreline still right with sigmas that cover it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.config import NavConfig
from pipe_nav_core.evaluation import score
from pipe_nav_core.gaps import fill_short_holes
from pipe_nav_core.imu_faults import find_imu_faults
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.pipeline import Outputs, load_log, smooth_bag

BAGS = Path(__file__).resolve().parents[1] / "bags"


@pytest.fixture(scope="module")
def log():
    return load_log(BAGS / "sample.mcap")[0]


def _imu(log, at: float, dur: float, gyro=None, accel=None, drop: bool = False):
    imu, t0 = log.imu, log.imu.t[0]
    k = (imu.t > t0 + at) & (imu.t < t0 + at + dur)
    if drop:
        return dataclasses.replace(log, imu=imu.slice(~k))
    g, a = imu.gyro.copy(), imu.accel.copy()
    if gyro is not None:
        g[k] = gyro(k.sum())
    if accel is not None:
        a[k] = accel(k.sum(), a[k])
    return dataclasses.replace(log, imu=dataclasses.replace(imu, gyro=g, accel=a))


rng = np.random.default_rng(1)
SHOCK = {"gyro": lambda n: np.clip(rng.normal(0, 30, (n, 3)), -34.9, 34.9),
         "accel": lambda n, a: np.clip(rng.normal(0, 120, (n, 3)), -156.9, 156.9)}  # fmt: skip


def _pinned(n, a):
    a = a.copy()
    a[:, 0] = 78.4  # +8 g: the accelerometer's range limit
    return a


def test_a_clean_imu_has_no_fault(log):
    assert find_imu_faults(log)[1] == []
    assert fill_short_holes(log)[1] == 0


@pytest.mark.parametrize(
    ("damage", "named", "max_h"),
    [
        (lambda lg: _imu(lg, 100.0, 5.0, **SHOCK), "IMU shock for 4.98 s", 0.06),
        (lambda lg: _imu(lg, 70.0, 0.2, accel=_pinned), "IMU saturated", 0.15),
        (lambda lg: _imu(lg, 100.0, 0.3, drop=True), "filled by interpolation", 0.05),
        (lambda lg: _imu(lg, 70.0, 0.95, drop=True), "data gap of 1.0 s", 0.15),
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
