"""Which sensor error makes a scenario's error: the error budget of a simulated run.

The scenario is simulated again with one error source removed at a time (the IMU error-free,
the odometer exact, both), the markers surveyed exactly, and each run smoothed with the
scenario's own estimator settings; the maximum horizontal and vertical errors and the
smoother's own vertical sigma at the worst point say what the remaining error comes from and
whether the sigmas cover it. The simulator draws each sensor's errors from its own random
stream, so removing one source leaves the others' realizations as they were.

With ``imu_grade`` the run is simulated and smoothed with another IMU grade (the sensor and
the estimator's model alike): whether a target the scenario's own IMU misses is a limit of
that IMU or of the estimator.

``python -m pipe_nav_core.bench.sources undulation90 --seed 1 [--imu-grade industrial]``
prints a Markdown table.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io.centreline import interpolate_trajectory
from pipe_nav_core.model.sensors import GRADES
from pipe_nav_core.model.sensors import imu_grade as imu_grade_spec
from pipe_nav_core.sim import Scenario, get_scenario, simulate
from pipe_nav_core.smooth.centreline import interpolate_enu
from pipe_nav_core.smooth.passes import smooth_log

CASES = ("as simulated", "IMU error-free", "odometer exact", "both exact")
# both sensors exact, the markers as simulated (their survey and passage-time errors): the
# error the markers alone leave, the floor of every smoother on the run (the accuracy bench's
# "markers-only limit")
MARKERS_ONLY = "markers only"


def variant(scenario: Scenario, case: str) -> Scenario:
    """The scenario with the error sources of ``case`` removed: one of CASES (the markers
    surveyed exactly besides) or MARKERS_ONLY (the IMU and the odometer exact, the markers'
    survey and passage-time errors kept)."""
    if case not in (*CASES, MARKERS_ONLY):
        raise ValueError(f"unknown case {case!r}; choose one of {', '.join(CASES)}")
    sc = scenario
    if case != MARKERS_ONLY:
        sc = replace(sc, survey_sigma_h=0.0, survey_sigma_v=0.0)
    if case in ("IMU error-free", "both exact", MARKERS_ONLY):
        spec = scenario.imu_spec or imu_grade_spec(scenario.imu_grade)
        sc = replace(sc, imu_spec=spec.scaled(0.0))
    if case in ("odometer exact", "both exact", MARKERS_ONLY):
        sc = replace(sc, odo_scale_sigma=0.0, odo_slip_interval=1e9, odo_tick=1e-6)
    if case in ("odometer exact", "both exact"):
        sc = replace(sc, marker_time_sigma=0.0)
    return sc


def error_budget(
    name: str, seed: int = 1, cases: Sequence[str] = CASES, imu_grade: str | None = None
) -> list[dict[str, float | str]]:
    """One row per case: max horizontal and vertical error (m) against the truth, the
    smoother's vertical one-sigma (m) where the vertical error is largest and its largest
    horizontal one-sigma between the markers (m). imu_grade: simulate and smooth the
    scenario with this IMU grade instead of its own (model.sensors.GRADES)."""
    scenario = get_scenario(name)
    if imu_grade is not None:
        imu_grade_spec(imu_grade)  # a clear ValueError for an unknown grade
        scenario = replace(scenario, imu_grade=imu_grade, imu_spec=None)
    config = NavConfig.from_dict(scenario.estimator_settings())
    rows: list[dict[str, float | str]] = []
    for case in cases:
        run = simulate(variant(scenario, case), seed=seed)
        result = smooth_log(run.log, config, method="rts")
        s = score(result.centreline, run.truth, run.log.markers, datum=result.datum)
        truth = run.truth
        t = truth.t[np.r_[True, np.diff(truth.distance) > 0]]  # moving: one time per place
        err_v = (interpolate_enu(result.centreline, t, result.datum)
                 - interpolate_enu(truth, t, result.datum))[:, 2]  # fmt: skip
        at = interpolate_trajectory(result.centreline, t[[int(np.argmax(np.abs(err_v)))]])
        sigma_v = float(np.asarray(at.sigma_enu).reshape(-1, 3)[0, 2])
        sigma_h = float(result.summary["max_sigma_h_between_markers_m"])  # type: ignore[arg-type]
        rows.append({"case": case, "max_h": s.max_h, "max_v": s.max_v, "sigma_v": sigma_v,
                     "sigma_h": sigma_h})  # fmt: skip
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pipe_nav_core.bench.sources SCENARIO [--seed N]``: the table on stdout."""
    ap = argparse.ArgumentParser(prog="python -m pipe_nav_core.bench.sources",
                                 description=__doc__.splitlines()[0])  # fmt: skip
    ap.add_argument("scenario", help="a simulator scenario (pipe-nav simulate --help lists them)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--imu-grade",
        choices=sorted(GRADES),
        help="simulate and smooth with this IMU grade instead of the scenario's",
    )
    args = ap.parse_args(argv)
    imu = f", {args.imu_grade} IMU" if args.imu_grade else ""
    print(f"{args.scenario}, seed {args.seed}{imu}, markers surveyed exactly, rts\n")
    print("| case | max h cm | max v cm | sigma v there cm | max sigma h cm |\n"
          "|---|---|---|---|---|")  # fmt: skip
    for r in error_budget(args.scenario, args.seed, imu_grade=args.imu_grade):
        print(f"| {r['case']} | {100 * float(r['max_h']):.1f} | {100 * float(r['max_v']):.1f} "
              f"| {100 * float(r['sigma_v']):.1f} | {100 * float(r['sigma_h']):.1f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
