"""The products benchmark (bench_products.py): scoring against the exact geometry in true
chainage, one real case end to end, the verdict, and the hook into ``pipe-nav bench``."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
from pipe_nav_core.app.cli import build_parser
from pipe_nav_core.bench import accuracy as bench
from pipe_nav_core.bench import products as bench_products
from pipe_nav_core.products import integrity_report
from pipe_nav_core.sim import simulate
from pipe_nav_core.sim.truth_products import run_config


@pytest.fixture(scope="module")
def bends_run():
    return simulate("bends_test", seed=1)


def test_true_chainage_is_the_pigs(bends_run):
    s_of_t = bench_products.true_chainage(bends_run)
    tr = bends_run.truth
    idx = np.arange(0, len(tr.t), 997)
    assert np.asarray(s_of_t(tr.t[idx])) == pytest.approx(tr.distance[idx], abs=1e-9)


def test_products_of_the_true_trajectory_score_as_exact(bends_run):
    """The products computed from the simulator's own trajectory: every bend found at its exact
    angle and apex, strain exact away from bends; so the scoring compares like with like."""
    cfg = run_config(bends_run)
    report = integrity_report(bends_run.truth, cfg)
    r = bench_products.score_products(bends_run, report, cfg, elapsed=0.5)
    assert r["bends_true"] == 14 and r["bends_found"] == 14
    assert r["bends_false"] == 0 and r["missed"] == [] and r["false"] == []
    assert r["angle_err_max_deg"] < 1e-6
    assert r["apex_err_max_m"] < 0.1
    assert r["strain_rms_off_bends_ue"] < 1e-3
    assert r["features_found"] == r["features_true"] > 0 and r["features_false"] == 0
    assert abs(r["feature_peak_err_max_pct"]) < 0.1
    assert r["window_m"] == pytest.approx(3 * 0.3239)
    duration = bends_run.log.imu.t[-1] - bends_run.log.imu.t[0]
    assert r["x_real_time"] == pytest.approx(duration / 0.5)
    # the elastic and 40 D bends' radii are exact; the short (3-5 D) ones are limited by the
    # products' fine window, which the radius error column shows
    elastic = [m for m in r["matched"] if m["radius_m"] > 10.0]
    assert elastic and all(abs(m["est_radius_m"] / m["radius_m"] - 1) < 1e-3 for m in elastic)


def test_one_real_case_scores_finite_numbers_within_sanity_bounds():
    case = next(c for c in bench_products.CASES if c.scenario == "strain_span")
    rows = bench_products.run_case(case, "tactical", seed=1)
    assert [r["variant"] for r in rows] == ["default", "5 m"]
    for r in rows:
        assert r["grade"] == "tactical" and r["length_m"] == 200.0
        assert math.isfinite(r["strain_rms_ue"]) and 0.0 < r["strain_rms_ue"] < 50.0
        assert r["strain_rms_ue"] <= r["strain_max_ue"] < 500.0
        assert r["bends_true"] == 0 and r["bends_false"] == 0
        assert r["x_real_time"] > 10.0 and r["smooth_seconds"] > 0.0
    default, five = rows
    assert default["window_m"] == pytest.approx(3 * 0.914) and five["window_m"] == 5.0
    # the settlement (0.141 % window-mean peak at 2.74 m) is found, its peak within 10 %
    assert default["features_true"] == default["features_found"] == 1
    assert default["movement_features_found"] == 1
    assert abs(default["movement_peak_err_max_pct"]) < 10.0
    assert default["verdict"] == "met" and five["verdict"] == "met"
    md = bench_products.markdown(rows, "pipe-nav bench --products-only")
    lines = [x for x in md.splitlines() if x.startswith("| strain_span | tactical |")]
    assert len(lines) == 2 and all(x.endswith("| met |") for x in lines)
    json.dumps(rows, default=float)  # the JSON payload


def test_verdict_names_what_is_missed():
    row = {"judge": "bends", "bends_true": 10, "bends_found": 9, "bends_false": 1,
           "angle_err_max_deg": 0.25, "apex_err_max_m": 0.1, "movement_features_true": 1,
           "movement_features_found": 1, "movement_peak_err_max_pct": -12.0}  # fmt: skip
    assert bench_products.verdict(row) == (
        "NOT met: 1 missed, 1 false, angle 0.25°, feature peak -12 %"
    )
    ok = {**row, "bends_found": 10, "bends_false": 0, "angle_err_max_deg": 0.05,
          "movement_peak_err_max_pct": 3.0}  # fmt: skip
    assert bench_products.verdict(ok) == "met"
    strain = {"judge": "strain", "strain_rms_ue": 60.0}
    assert bench_products.verdict(strain) == "NOT met: RMS 60 µε"
    assert bench_products.verdict({"judge": "strain", "strain_rms_ue": 20.0}) == "met"
    assert bench_products.verdict({"judge": ""}) == ""


def test_bench_products_flags(tmp_path, monkeypatch):
    args = build_parser().parse_args(["bench", "--products-only", "--quick"])
    assert args.products_only and args.quick and not args.products
    assert build_parser().parse_args(["bench", "--products"]).products
    fake = [{"scenario": "strain_span", "grade": "tactical", "variant": "default",
             "error": "boom", "verdict": "ERROR: smoothing failed (X)"}]  # fmt: skip
    seen = {}

    def fake_run(quick=False, **_kw):
        seen["quick"] = quick
        return fake

    monkeypatch.setattr(bench_products, "run", fake_run)
    ns = argparse.Namespace(
        products=False, products_only=True, quick=True, speed=False, speed_only=False,
        scenarios=None, pipe_seed=None, out=str(tmp_path / "B.md"),
        json=str(tmp_path / "b.json"),
    )  # fmt: skip
    assert bench.main(ns) == 0
    md = (tmp_path / "B.md").read_text()
    assert "## Bends, curvature and strain against the exact geometry" in md
    assert "| strain_span | tactical | default |" in md and "ERROR" in md
    assert "| drag180" not in md  # products only: no accuracy rows
    assert json.loads((tmp_path / "b.json").read_text())["products"] == fake
    assert seen == {"quick": True}
