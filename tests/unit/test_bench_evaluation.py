"""Scoring against the truth, on synthetic trajectories whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pipe_nav_core.bench.evaluation import (
    Score,
    errors_enu,
    profile_sag_depth,
    sag_depth,
    score,
)
from pipe_nav_core.geo import earth
from pipe_nav_core.types import Datum, Marker, Trajectory

LAT0, LON0, H0 = math.radians(36.0), math.radians(104.0), 1500.0
DATUM = Datum(LAT0, LON0, H0)


def make_traj(t: np.ndarray, enu: np.ndarray, distance: np.ndarray, sigma=None) -> Trajectory:
    lat, lon, h = earth.enu_to_geodetic(enu, LAT0, LON0, H0)
    n = len(t)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return Trajectory(t, lat, lon, h, np.zeros((n, 3)), q, distance, sigma_enu=sigma)


@pytest.fixture()
def truth() -> Trajectory:
    # 300 m north-east at 1 m/s, 10 Hz
    t = np.arange(0.0, 300.0, 0.1)
    d = t * 1.0
    enu = np.stack([d / math.sqrt(2), d / math.sqrt(2), 0.01 * d], axis=1)
    return make_traj(t, enu, d)


def shifted(truth: Trajectory, offset, t=None, sigma=None) -> Trajectory:
    t = truth.t if t is None else t
    d = t * 1.0
    enu = np.stack([d / math.sqrt(2), d / math.sqrt(2), 0.01 * d], axis=1) + np.asarray(offset)
    return make_traj(t, enu, d, sigma)


def markers_at(ts) -> list[Marker]:
    return [Marker(f"agm_{k:02d}", float(x), LAT0, LON0, H0) for k, x in enumerate(ts)]


def test_identical_trajectories_score_zero(truth):
    s = score(truth, truth)
    assert isinstance(s, Score)
    assert s.max_h == pytest.approx(0.0, abs=1e-9) and s.max_v == pytest.approx(0.0, abs=1e-9)
    assert s.n == len(truth)
    assert math.isnan(s.inside_3sigma) and math.isnan(s.ratio_between_markers)


def test_a_3cm_east_shift_gives_3cm_horizontal(truth):
    s = score(shifted(truth, [0.03, 0.0, 0.0]), truth, datum=DATUM)
    assert s.max_h == pytest.approx(0.03, abs=1e-6)
    assert s.rms_h == pytest.approx(0.03, abs=1e-6)
    assert s.max_v == pytest.approx(0.0, abs=1e-6)
    s = score(shifted(truth, [0.0, -0.04, 0.05]), truth)
    assert s.max_h == pytest.approx(0.04, abs=1e-6)
    assert s.max_v == pytest.approx(0.05, abs=1e-6) and s.rms_v == pytest.approx(0.05, abs=1e-6)
    assert s.max_3d == pytest.approx(math.hypot(0.04, 0.05), abs=1e-6)


def test_comparison_is_by_time_with_interpolation(truth):
    # estimate at other instants (between the truth samples): still exact for a linear path
    t = np.arange(0.05, 299.0, 0.37)
    s = score(shifted(truth, [0, 0, 0], t=t), truth)
    assert s.max_h == pytest.approx(0.0, abs=1e-6) and s.n == len(t)
    # samples outside the truth's span are ignored
    t2 = np.concatenate([[-5.0, -1.0], t, [400.0]])
    s2 = score(shifted(truth, [0.02, 0, 0], t=t2), truth)
    assert s2.n == len(t)
    assert s2.max_h == pytest.approx(0.02, abs=1e-6)
    _, err, inside = errors_enu(shifted(truth, [0.02, 0, 0], t=t2), truth)
    assert not inside[0] and np.isnan(err[0]).all()
    # a time offset is an along-track error: 0.5 s late at 1 m/s = 0.5 m
    late = shifted(truth, [0, 0, 0], t=t)
    late.t = late.t + 0.5
    assert score(late, truth).max_h == pytest.approx(0.5, abs=1e-3)


def test_between_markers_and_the_one_to_n_figure(truth):
    # error grows from 0 at each marker to 5 cm in the middle of the 100 m spacing
    t = truth.t
    d = t * 1.0
    bump = 0.05 * np.sin(np.pi * (d % 100.0) / 100.0)
    enu = np.stack([d / math.sqrt(2), d / math.sqrt(2), 0.01 * d], axis=1)
    east_err = np.where(t <= 200.0, bump, 0.2)  # large error after the last marker
    enu[:, 0] += east_err
    est = make_traj(t, enu, d)
    s = score(est, truth, markers_at([0.0, 100.0, 200.0]))
    assert s.marker_spacing == pytest.approx(100.0, abs=1e-9)
    assert s.max_h_between_markers == pytest.approx(0.05, abs=1e-4)
    assert s.ratio_between_markers == pytest.approx(100.0 / 0.05, rel=1e-3)
    assert s.max_h == pytest.approx(0.2, abs=1e-6)
    # markers given out of order are sorted by time
    s2 = score(est, truth, markers_at([200.0, 0.0, 100.0])[::-1])
    assert s2.max_h_between_markers == s.max_h_between_markers
    assert "1:2000" in s.summary()


def test_inside_three_sigma(truth):
    n = len(truth)
    sigma = np.full((n, 3), 0.01)
    sigma[: n // 2] = 0.001  # first half claims 1 mm: a 2 cm error is outside
    est = shifted(truth, [0.02, 0.0, 0.0], sigma=sigma)
    assert score(est, truth).inside_3sigma == pytest.approx(0.5, abs=1e-3)
    sigma2 = np.full((n, 3), 0.01)
    sigma2[:, 2] = 0.001
    est2 = shifted(truth, [0.0, 0.0, 0.02], sigma=sigma2)  # vertical error outside 3 sigma
    assert score(est2, truth).inside_3sigma == 0.0


def test_the_sigma_where_the_error_is_largest(truth):
    """The estimate's own sigma is read at the sample of its largest error, each axis on its
    own: whether the estimator expected an error of that size there."""
    n = len(truth)
    bump = np.exp(-(((np.arange(n) - 0.3 * n) / 20.0) ** 2))  # horizontal, at 30 % of the run
    dip = np.exp(-(((np.arange(n) - 0.7 * n) / 20.0) ** 2))  # vertical, at 70 %
    sigma = np.empty((n, 3))
    sigma[:, 0] = sigma[:, 1] = 0.01 + 0.01 * np.arange(n) / n  # grows along the run
    sigma[:, 2] = 0.005 + 0.02 * np.arange(n) / n
    d = truth.t * 1.0
    enu = np.stack([d / math.sqrt(2), d / math.sqrt(2), 0.01 * d], axis=1)
    off = np.stack([0.03 * bump, np.zeros(n), -0.02 * dip], axis=1)
    est = make_traj(truth.t, enu + off, d, sigma)
    s = score(est, truth)
    i, j = int(np.argmax(bump)), int(np.argmax(dip))
    assert s.max_h == pytest.approx(0.03, abs=1e-4) and s.max_v == pytest.approx(0.02, abs=2e-4)
    assert s.sigma_h_at_max_h == pytest.approx(math.hypot(sigma[i, 0], sigma[i, 1]), rel=1e-3)
    assert s.sigma_v_at_max_v == pytest.approx(sigma[j, 2], rel=1e-3)
    assert math.isnan(score(shifted(truth, 0.01), truth).sigma_h_at_max_h)  # no sigmas


def test_sag_depth_of_profiles():
    x = np.linspace(0.0, 100.0, 1001)
    z = -0.2 * np.sin(np.pi * x / 100.0) ** 2 + 0.03 * x  # sag on a grade
    pts = np.stack([x * 0.6, x * 0.8, z], axis=1)
    assert profile_sag_depth(pts) == pytest.approx(0.2, abs=1e-6)
    assert profile_sag_depth(np.stack([x, 0 * x, -z + 0.06 * x], axis=1)) == pytest.approx(0.0)
    with pytest.raises(ValueError):
        profile_sag_depth(pts[:2])
    # on a trajectory, with chainage limits; a level pipe has none however long
    enu = np.stack([x, 0 * x, -0.3 * np.sin(np.pi * x / 100.0) ** 2], axis=1)
    traj = make_traj(x, enu, x)
    # (built in the flat ENU plane: heights add the Earth's curvature, L^2 / 8R = 0.2 mm)
    assert sag_depth(traj) == pytest.approx(0.3, abs=1e-3)
    assert sag_depth(traj, start=25.0, end=75.0) == pytest.approx(0.15, abs=1e-3)
    long_t = np.linspace(0.0, 10_000.0, 101)
    flat = np.stack([long_t, 0 * long_t, 0 * long_t], 1)
    lat, lon, h = earth.enu_to_geodetic(flat, LAT0, LON0, H0)
    level = Trajectory(
        long_t, lat, lon, np.full_like(long_t, H0), np.zeros((101, 3)),
        np.tile([0, 0, 0, 1.0], (101, 1)), long_t,
    )
    assert sag_depth(level) == pytest.approx(0.0, abs=1e-9)


def test_simulated_truth_and_markers():
    from pipe_nav_core.sim import get_scenario, simulate

    run = simulate(get_scenario("sag104").with_length(30.0), seed=1)
    s = score(run.truth, run.truth, run.log.markers, datum=run.datum)
    assert s.max_h == pytest.approx(0.0, abs=1e-9)
    assert s.marker_spacing == pytest.approx(30.0, abs=0.1)
    assert s.ratio_between_markers == math.inf
