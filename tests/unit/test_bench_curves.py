"""The gentle-curve bench's scenarios: one plan curve in place of the plan bends."""

from __future__ import annotations

import math

from pipe_nav_core.bench.curves import CASES, curved
from pipe_nav_core.sim import get_scenario
from pipe_nav_core.sim.geometry import Bend, Sag


def test_a_curved_scenario_has_its_one_plan_curve_and_keeps_the_rest():
    base = get_scenario("undulation90")  # a plan bend of 6 deg and a sag
    sc = curved(base, math.radians(2.0), 1500.0, 20.0)
    plan = [f for f in sc.features if isinstance(f, Bend) and f.plane == "h"]
    assert plan == [Bend(20.0, math.radians(2.0), 1500.0, "h")]
    assert [f for f in sc.features if isinstance(f, Sag)] == [
        f for f in base.features if isinstance(f, Sag)
    ]
    assert sc.survey_sigma_h == sc.survey_sigma_v == 0.0
    for name, angle, radius, start in CASES:  # every curve lies inside its pipe
        assert start + radius * math.radians(angle) > get_scenario(name).length / 2
        assert start < get_scenario(name).length
