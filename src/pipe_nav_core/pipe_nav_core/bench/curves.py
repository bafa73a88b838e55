"""Gentle curves: whether the straight-pipe model holds a curve of a kilometre's radius straight.

A pipe's straight sections come from the previous pass's path (model.measurements.
straight_pipe.sections). A curve of 1500 m radius turns 0.67 mrad a metre, too little for the
2 m test to see through a consumer gyro's noise, but 35 mrad over 52 m. Held straight, it leaves
a confident wrong centreline. Each case puts one such curve in plan into a scenario (its own
plan bends taken out), markers surveyed exactly. The run is smoothed with the scenario's own
settings; the largest horizontal error is then set against the smoother's sigma there.

``python -m pipe_nav_core.bench.curves [--seeds 1 2 3]`` prints a Markdown table.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import replace

from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.sim import Scenario, get_scenario, simulate
from pipe_nav_core.sim.geometry import Bend
from pipe_nav_core.smooth.passes import smooth_log

# (scenario, plan angle deg, radius m, start m): the curve, and where it begins
CASES = (
    ("undulation90", 2.0, 1500.0, 20.0),
    ("undulation90", 3.0, 3000.0, 10.0),
    ("undulation90", 1.0, 3000.0, 40.0),
    ("undulation90", 1.0, 5000.0, 30.0),
    ("sag104", 2.0, 1500.0, 20.0),
    ("sag104", 1.0, 5000.0, 20.0),
)


def curved(scenario: Scenario, angle: float, radius: float, start: float) -> Scenario:
    """The scenario with its plan bends replaced by one curve of ``angle`` (rad) and ``radius``
    (m) from chainage ``start`` (m), the markers surveyed exactly."""
    kept = tuple(f for f in scenario.features if not (isinstance(f, Bend) and f.plane == "h"))
    return replace(scenario, features=(*kept, Bend(start, angle, radius, "h")),
                   survey_sigma_h=0.0, survey_sigma_v=0.0)  # fmt: skip


def run_case(scenario: Scenario, seed: int) -> tuple[float, float, float]:
    """(largest horizontal error m, the smoother's horizontal sigma there m, gentle curves
    found m) of one run smoothed with rts."""
    run = simulate(scenario, seed=seed)
    res = smooth_log(run.log, NavConfig.from_dict(scenario.estimator_settings()), method="rts")
    s = score(res.centreline, run.truth, datum=res.datum)
    found = float(res.summary.get("gentle_curves_m", 0.0))  # type: ignore[arg-type]
    return s.max_h, s.sigma_h_at_max_h, found


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipe_nav_core.bench.curves", description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = ap.parse_args(argv)
    print("| scenario | curve | seed | max h [cm] | sigma there [cm] | error / sigma | found [m] |")
    print("|---|---|---|---|---|---|---|")
    for name, angle, radius, start in CASES:
        sc = curved(get_scenario(name), math.radians(angle), radius, start)
        for seed in args.seeds:
            h, s, found = run_case(sc, seed)
            print(f"| {name} | {angle:g} deg, R {radius:g} m from {start:g} m | {seed} "
                  f"| {100 * h:.1f} | {100 * s:.1f} | {h / max(s, 1e-9):.1f} | {found:.1f} |",
                  flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
