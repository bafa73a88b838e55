"""Multi-run fusion (products/fusion.py, pipe-nav fuse): one sparse least-squares problem over
the shared pipe and each run's own error; the fused line beats a single run."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.cli import main
from pipe_nav_core.bench.runs import (
    FUSION_GRADE,
    FUSION_MARKER_SPACING_M,
    _error_h,
    smoothed,
)
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io.centreline import CENTRELINE_HEADER
from pipe_nav_core.products.fusion import fuse_runs
from pipe_nav_core.sim import get_scenario

SCN = replace(get_scenario("demo"), marker_spacing=FUSION_MARKER_SPACING_M,
              imu_grade=FUSION_GRADE)  # fmt: skip
CFG = NavConfig.from_dict(SCN.estimator_settings())


@pytest.fixture(scope="module")
def runs():
    return [smoothed(SCN, seed, CFG) for seed in (1, 2, 3, 4, 5)]


def _rms(x):
    return float(np.sqrt(np.mean(np.asarray(x) ** 2)))


def test_five_fused_runs_beat_each_run_alone(runs):
    fused = fuse_runs([sm for _, sm in runs])
    err = _error_h(fused.centreline, fused.datum, runs[0][0])
    singles = [_rms(_error_h(sm.trajectory, sm.datum, run)) for run, sm in runs]
    # below the mean single run and below the reference run alone (whose chainage and map
    # frame the fused line keeps); the markers' shared survey error (2 cm) stays, and the
    # single runs now come near it. Measured: fused 2.19 cm rms against 2.40 / 2.36 / 2.74 /
    # 2.17 / 3.56 (with the straight-pipe rate update only: 2.38 against 3.38 / 2.46 / 2.71 /
    # 2.24 / 3.78; without either 3.01 against 6.26 / 4.30 / 2.62 / 2.44 / 3.86)
    assert _rms(err) < 0.9 * np.mean(singles), (_rms(err), singles)
    assert _rms(err) < 0.95 * singles[0], (_rms(err), singles)
    # the residuals: each run's own error, what the fused line removed from it
    assert [r.index for r in fused.residuals] == [1, 2, 3, 4, 5]
    assert all(r.welds_matched >= 20 for r in fused.residuals)
    for (run, sm), r in zip(runs, fused.residuals, strict=True):
        assert 0.3 * _rms(_error_h(sm.trajectory, sm.datum, run)) < r.rms_h < 0.2
    assert fused.run_errors.shape == (5, len(fused.centreline.t), 3)
    assert not fused.notes


def test_the_fused_sigma_falls_with_the_runs_and_the_line_is_complete(runs):
    sig = []
    for n in (1, 2, 5):
        line = fuse_runs([sm for _, sm in runs[:n]]).centreline
        s = line.sigma_enu
        assert np.isfinite(s).all() and (s > 0).all()
        sig.append(float(np.mean(np.hypot(s[:, 0], s[:, 1]))))
        assert np.all(np.diff(line.distance) == pytest.approx(0.5))
        assert np.all(np.diff(line.t) >= 0)
    assert sig[0] > sig[1] > sig[2]
    one = runs[0][1]
    alone = np.mean(np.hypot(one.trajectory.sigma_enu[:, 0], one.trajectory.sigma_enu[:, 1]))
    assert sig[0] == pytest.approx(alone, rel=0.25)  # one run: its own sigma back


def test_one_run_fused_is_that_run(runs):
    run, sm = runs[0]
    fused = fuse_runs([sm])
    assert fused.residuals[0].max_h < 0.01
    assert abs(_rms(_error_h(fused.centreline, fused.datum, run))
               - _rms(_error_h(sm.trajectory, sm.datum, run))) < 0.01  # fmt: skip


def test_bad_settings_are_refused(runs):
    with pytest.raises(ValueError, match="correlation_length"):
        fuse_runs([sm for _, sm in runs[:2]], correlation_length=0.0)
    with pytest.raises(ValueError, match="at least one run"):
        fuse_runs([])


def test_pipe_nav_fuse_writes_a_centreline_csv(tmp_path: Path, capsys):
    from pipe_nav_core.io import write_sensor_bag
    from pipe_nav_core.sim import simulate

    short = SCN.with_length(120.0)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({k: list(v) if isinstance(v, tuple) else v
                               for k, v in short.estimator_settings().items()}))  # fmt: skip
    bags = []
    for seed in (1, 2, 3):
        raw = tmp_path / f"r{seed}.mcap"
        write_sensor_bag(str(raw), simulate(short, seed).log)
        bags.append(str(tmp_path / f"r{seed}_smoothed.mcap"))
        assert main(["smooth", str(raw), "--out", bags[-1], "--config", str(cfg)]) == 0
    capsys.readouterr()
    out = tmp_path / "FUSED.csv"
    assert main(["fuse", *bags, "--out", str(out), "--workers", "2"]) == 0
    text = capsys.readouterr().out
    assert "3 runs fused" in text and text.count("_smoothed.mcap") == 3
    with out.open() as f:
        header = f.readline().strip()
        rows = list(csv.DictReader(f, fieldnames=header.split(",")))
    assert header == CENTRELINE_HEADER
    assert len(rows) > 200 and all(r["sigma_east_m"] for r in rows)
    assert float(rows[-1]["distance_m"]) > 110.0
    assert main(["fuse", *bags, "--out", str(tmp_path / "F2.csv"), "--spacing", "-1"]) == 2
    assert "spacing" in capsys.readouterr().err


def test_the_fused_sigma_covers_the_fused_error(runs):
    """The markers' survey error is the same in every run: the fused sigma keeps it."""
    from pipe_nav_core.io.centreline import interpolate_trajectory
    from pipe_nav_core.io.rosmsg import enu_of

    fused = fuse_runs([sm for _, sm in runs])
    run = runs[0][0]
    line = fused.centreline
    truth = interpolate_trajectory(run.truth, line.t)
    err = enu_of(fused.datum, line.lat, line.lon, line.h) - enu_of(
        fused.datum, truth.lat, truth.lon, truth.h
    )
    z = np.abs(err) / np.asarray(line.sigma_enu)
    assert np.mean(np.all(z < 3.0, axis=1)) >= 0.95, np.percentile(z, [50, 95, 99], axis=0)
