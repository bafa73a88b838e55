"""The straight-pipe and section-direction updates (on by default) on the project's simulator:
only the passes about a reference have them, and on the consumer-grade drag test (seed 001,
markers at both ends only) they take the horizontal error between the markers down by more
than half, the section direction alone by a sixth of what is left; on the rolling pig of the
undulating pipe they show the boresight; a gentle curve is not held straight."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.model.measurements.straight_pipe import sections
from pipe_nav_core.model.state import SV_DIST, SV_T, layout_for
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.sim.geometry import Bend
from pipe_nav_core.smooth.forward import run_forward
from pipe_nav_core.smooth.heading import smoothing_config
from pipe_nav_core.smooth.passes import smooth_log, smoothed_states
from pipe_nav_core.smooth.rts import rts_packed
from pipe_nav_core.smooth.two_filter import backward_pass, backward_sections, end_azimuth


@pytest.fixture(scope="module")
def drag():
    run = simulate("drag180", seed=3)
    cfg = NavConfig.from_dict(run.scenario.estimator_settings())
    rate_only = replace(cfg, straight_pipe_wander=0.0)
    return run, replace(rate_only, straight_pipe_sigma=0.0), rate_only, cfg


def test_only_passes_about_a_reference_apply_it(drag):
    run, _, _, on = drag
    cfg = smoothing_config(run.log, replace(on, filter_rate_hz=on.smoothing_rate_hz()))
    first = run_forward(run.log, cfg)
    assert not any(first.diagnostics().get(f"accepted_{k}", 0) for k in ("straight", "direction"))
    rec = first.recording
    e, _ = rts_packed(rec.rts_chunks(), rec.dx, rec.format, var_cols=rec.pose)
    ref = smoothed_states(rec, e, layout_for(cfg))
    second = run_forward(run.log, cfg, reference=ref).diagnostics()
    epochs = second["epochs"]
    # the 180 m pipe is straight but for its 8 bends and their margins: most moving epochs
    assert second["accepted_straight"] > 0.5 * epochs
    assert second.get("rejected_straight", 0) < 0.05 * second["accepted_straight"]
    # the section direction's rows: one per moving epoch of a straight section, and the state
    # restarted at each section's start (the azimuth held to within milliradians of the axis)
    assert second["accepted_direction"] > 0.5 * epochs
    assert second.get("rejected_direction", 0) < 0.05 * second["accepted_direction"]
    # two-filter's backward filter has no reference: it takes the forward's sections, in its
    # own chainage (zero at the receive trap), and applies both updates as often
    back = backward_pass(run.log, cfg, ref[:, SV_T], end_azimuth(ref[-1]),
                         straight=backward_sections(sections(ref, cfg)[:2],
                                                    ref[-1, SV_DIST])).diagnostics()  # fmt: skip
    for kind in ("straight", "direction"):
        assert back[f"accepted_{kind}"] > 0.9 * second[f"accepted_{kind}"], kind
        assert back.get(f"rejected_{kind}", 0) < 0.05 * back[f"accepted_{kind}"], kind
    assert (
        "accepted_direction"
        not in backward_pass(run.log, cfg, ref[:, SV_T], end_azimuth(ref[-1])).diagnostics()
    )


def test_it_takes_the_horizontal_error_down(drag):
    run, off, rate_only, on = drag
    err = {}
    for name, cfg in (("off", off), ("rate_only", rate_only), ("on", on)):
        res = smooth_log(run.log, cfg, method="rts")
        s = score(res.centreline, run.truth, run.log.markers, datum=res.datum)
        err[name] = (s.max_h, s.max_v, s.inside_3sigma)
        assert (res.summary["straight_pipe_updates"] > 500) == (name != "off")  # of 1428 epochs
        assert (res.summary["section_direction_updates"] > 500) == (name == "on")
    # measured: 12.6 -> 6.4 -> 5.1 cm horizontal
    assert err["rate_only"][0] < 0.67 * err["off"][0]
    assert err["on"][0] < 0.85 * err["rate_only"][0]
    for name in err:
        assert err[name][2] >= 0.95, name  # the sigmas still cover the errors
    # the vertical, which the markers' 1.2 cm survey error mostly makes here, is not the worse
    # for them over seeds 1-3 (one seed's moves by a tenth either way: seed 3's 1.8 -> 2.0 cm);
    # measured: mean max v 1.67 cm off, 1.52 cm on (over 12 seeds 2.05 and 1.59)
    v = {"off": [err["off"][1]], "on": [err["on"][1]]}
    for seed in (1, 2):
        other = simulate("drag180", seed=seed)
        for name, cfg in (("off", off), ("on", on)):
            res = smooth_log(other.log, cfg, method="rts")
            s = score(res.centreline, other.truth, other.log.markers, datum=res.datum)
            v[name].append(s.max_v)
    assert np.mean(v["on"]) < 1.1 * np.mean(v["off"])


def test_a_rolling_pig_shows_its_boresight():
    """The consumer-grade undulating pipe (seed 1, no wheel slips, markers surveyed exactly):
    the pig rolls from 20 to 160 deg, so a boresight error held by rows on base_link x turned
    the line one way before 90 deg of roll and the other way after (10.0 cm h, 9.5 cm v).
    With the rows on the direction of travel u(boresight) the roll shows the boresight."""
    sc = replace(get_scenario("undulation90"), survey_sigma_h=0.0, survey_sigma_v=0.0,
                 odo_slip_interval=1e9)  # fmt: skip
    run = simulate(sc, seed=1)
    res = smooth_log(run.log, NavConfig.from_dict(sc.estimator_settings()), method="rts")
    s = score(res.centreline, run.truth, run.log.markers, datum=res.datum)
    # measured: 4.04 cm h, 0.41 cm v, 98.8 % inside 3 sigma
    assert s.max_h < 0.06 and s.max_v < 0.02
    assert s.inside_3sigma >= 0.95


def test_a_gentle_curve_is_not_held_straight():
    """The undulating pipe with its 6 deg bend of 150 m radius replaced by a 2 deg curve of
    1500 m radius from 20 m (0.67 mrad a metre: straight by the 2 m test, 35 mrad in all),
    seed 2, markers surveyed exactly. Sections taken from that test alone held the curve
    straight: 49 cm horizontal error at 14 sigma. The curve is found and left out."""
    base = get_scenario("undulation90")
    features = tuple(f for f in base.features if not isinstance(f, Bend))
    sc = replace(base, features=(*features, Bend(20.0, math.radians(2.0), 1500.0, "h")),
                 survey_sigma_h=0.0, survey_sigma_v=0.0)  # fmt: skip
    run = simulate(sc, seed=2)
    res = smooth_log(run.log, NavConfig.from_dict(sc.estimator_settings()), method="rts")
    s = score(res.centreline, run.truth, run.log.markers, datum=res.datum)
    # measured: 2.5 cm h, 98.2 % inside 3 sigma; 53 m found curved, 453 straight-pipe updates
    assert s.max_h < 0.08
    assert s.inside_3sigma >= 0.95
    assert 40.0 < res.summary["gentle_curves_m"] < 70.0
    assert res.summary["straight_pipe_updates"] > 200  # the straight pipe each side keeps them
