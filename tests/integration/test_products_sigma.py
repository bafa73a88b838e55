"""The strain sigmas against the strain error in a Monte Carlo over seeds: smoothed simulated
runs, the estimated strain against the simulator's exact window-mean strain where the pig was
(through time: a chainage error is not a strain error)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from pipe_nav_core.bench.products import true_strain_at
from pipe_nav_core.config import NavConfig
from pipe_nav_core.products import integrity_report
from pipe_nav_core.sim import simulate
from pipe_nav_core.sim.scenarios import get_scenario
from pipe_nav_core.smooth.passes import smooth_log


def z_scores(name: str, grade: str, seeds: range) -> np.ndarray:
    out = []
    for seed in seeds:
        scn = replace(get_scenario(name), imu_grade=grade)
        run = simulate(scn, seed=seed)
        cfg = NavConfig.from_dict(scn.estimator_settings())
        rep = integrity_report(smooth_log(run.log, cfg).centreline, cfg)
        p = rep.profile
        truth = true_strain_at(run, p.t, rep.window, cfg.outer_diameter())
        inner = (p.distance > p.distance[0] + rep.window) & (
            p.distance < p.distance[-1] - rep.window
        )
        out.append(((rep.strain_pct - truth) / rep.sigma_strain_pct)[inner])
    return np.concatenate(out)


@pytest.mark.parametrize(("name", "grade"), [("strain_span", "industrial"), ("demo", "industrial"),
                                             ("strain_span", "consumer")])  # fmt: skip
def test_strain_sigmas_cover_the_strain_error(name, grade):
    z = np.abs(z_scores(name, grade, range(4)))
    assert len(z) > 1000
    assert np.mean(z < 3.0) >= 0.95 and np.mean(z < 2.0) >= 0.85, (np.mean(z < 3), np.mean(z < 2))
    assert 0.2 < np.median(z) < 1.5, np.median(z)  # and are not ten times too wide
