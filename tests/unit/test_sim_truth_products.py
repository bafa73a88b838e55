"""The simulator's exact integrity products (sim/truth_products.py) against hand-computed closed
forms: curvature of bends and sags, the window mean, the bend list, and the truth CSVs."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from pipe_nav_core.io.products_csv import BEND_COLUMNS, STRAIN_COLUMNS
from pipe_nav_core.model.sensors import imu_grade
from pipe_nav_core.products.curvature import windowed_curvature
from pipe_nav_core.sim import Bend, PipeGeometry, Sag, get_scenario, simulate
from pipe_nav_core.sim.geometry import _sag_amplitude
from pipe_nav_core.sim.truth_products import (
    SAG_MIDDLE_ANGLE,
    SAG_OUTER_ANGLE,
    point_curvature,
    strain_pct,
    truth_bends,
    truth_product_paths,
    window_curvature,
    write_truth_products,
)

DEG = math.pi / 180.0
LAT, LON, H = 0.6, 2.0, 100.0


def pipe(*features, pitch0=0.0, length=200.0, diameter=0.2):
    return PipeGeometry(length, LAT, LON, H, 0.7, pitch0, list(features), diameter=diameter)


def test_circular_bends_have_the_closed_form_curvature():
    r, ramp = 10.0, 1.0
    g = pipe(Bend(20.0, 30 * DEG, r, "h", ramp), Bend(80.0, -20 * DEG, 4.0, "v", ramp))
    arc_h = 30 * DEG * r
    k = point_curvature(g, [20.0 + ramp + 0.5 * (arc_h - ramp), 20.0 + 0.5 * ramp, 19.0, 60.0])
    # constant arc: 1/R to the right; mid-ramp: half (smootherstep(1/2) = 1/2); straight: 0
    assert k["horizontal"] == pytest.approx([1 / r, 0.5 / r, 0.0, 0.0], abs=1e-12)
    assert k["vertical"] == pytest.approx([0, 0, 0, 0], abs=1e-12)
    assert k["total"][0] == pytest.approx(1 / r, rel=1e-12)
    assert math.degrees(k["plane"][0]) == pytest.approx(90.0)
    # a vertical bend turning down: vertical -1/R, the centre of curvature below (180 deg)
    kv = point_curvature(g, [80.0 + ramp + 0.1])
    assert kv["vertical"][0] == pytest.approx(-1 / 4.0, rel=1e-12)
    assert math.degrees(kv["plane"][0]) == pytest.approx(180.0)
    # a horizontal bend on a slope: horizontal = cos(pitch) d(azimuth)/ds
    gs = pipe(Bend(20.0, 30 * DEG, r, "h", ramp), pitch0=12 * DEG)
    ks = point_curvature(gs, [25.0])
    assert ks["horizontal"][0] == pytest.approx(math.cos(12 * DEG) / r, rel=1e-12)
    assert strain_pct(ks["total"], 0.3)[0] == pytest.approx(100 * 0.15 * math.cos(12 * DEG) / r)


def test_sag_curvature_is_the_closed_form_with_lobes_at_thirds():
    length, depth = 40.0, 0.5
    g = pipe(Sag(50.0, length, depth, "v"))
    amp = _sag_amplitude(depth, length)
    x = np.array([0.1, 1 / 3, 0.5, 2 / 3, math.acos(0.25) / (2 * math.pi)])
    k = point_curvature(g, 50.0 + x * length)
    big_x = 2 * math.pi * x
    expected = -amp * math.pi / length * (np.cos(big_x) - np.cos(2 * big_x))
    assert k["vertical"] == pytest.approx(expected, abs=1e-12)
    assert k["vertical"][[1, 3]] == pytest.approx([0.0, 0.0], abs=1e-12)  # zero crossings
    assert k["vertical"][2] == pytest.approx(2 * amp * math.pi / length)  # middle lobe peak
    assert k["vertical"][4] == pytest.approx(-9 / 8 * amp * math.pi / length)  # outer peak
    bends = truth_bends(g, 0.0)
    assert [b.direction for b in bends] == ["over", "sag", "over"]
    assert [b.angle for b in bends] == pytest.approx(
        [SAG_OUTER_ANGLE * amp, SAG_MIDDLE_ANGLE * amp, SAG_OUTER_ANGLE * amp], rel=1e-9
    )
    assert [b.radius for b in bends] == pytest.approx(
        [length / (9 / 8 * amp * math.pi), length / (2 * amp * math.pi)] * 1
        + [length / (9 / 8 * amp * math.pi)], rel=1e-9
    )
    assert [b.start_m for b in bends] == pytest.approx([50.0, 50 + length / 3, 50 + 2 * length / 3])
    assert bends[1].apex_m == pytest.approx(70.0, abs=1e-6)
    # the outer lobes' apexes: the middle of their half-peak stretch, mirror images
    assert bends[0].apex_m - 50.0 == pytest.approx(90.0 - bends[2].apex_m, abs=1e-3)


def test_window_mean_equals_the_pointwise_curvature_on_a_long_arc():
    r = 100.0
    g = pipe(Bend(20.0, 20 * DEG, r, "h", 1.0), Bend(100.0, 15 * DEG, 60.0, "v", 1.0))
    s = np.array([30.0, 40.0, 45.0])  # windows inside the constant arc (21 to 54.9 m)
    for w in (0.5, 5.0, 10.0):
        k = window_curvature(g, s, w)
        assert k["total"] == pytest.approx(1 / r, rel=1e-9)
        assert k["horizontal"] == pytest.approx(1 / r, rel=1e-9)
        assert k["vertical"] == pytest.approx(0.0, abs=1e-12)
    kv = window_curvature(g, [110.0], 4.0)  # vertical arc 101 to 114.7 m
    assert kv["vertical"][0] == pytest.approx(1 / 60.0, rel=1e-9)
    assert math.degrees(kv["plane"][0]) == pytest.approx(0.0, abs=1e-9)
    # a bend shorter than the window: its whole angle over the window
    gs = pipe(Bend(50.0, 5 * DEG, 0.5, "h"))
    assert window_curvature(gs, [50.1], 3.0)["total"][0] == pytest.approx(5 * DEG / 3.0, rel=1e-9)
    # at the pipe's ends the window shrinks to the pipe
    assert window_curvature(g, [0.0], 2.0)["total"][0] == pytest.approx(0.0, abs=1e-15)


def test_window_mean_uses_the_estimators_formula():
    """Fed with the same axis, the estimator's windowed_curvature gives the exact window mean."""
    from pipe_nav_core.products.curvature import AxisTrack

    g = pipe(Bend(20.0, 30 * DEG, 2.0, "h"), Bend(21.0, -10 * DEG, 3.0, "v"), pitch0=5 * DEG)
    s = np.arange(0.0, 60.0, 0.001)
    lat, lon, h = g.position(s)
    track = AxisTrack(s, s, s, lat, lon, h, g.tangent_enu(s), 0 * s, 0 * s)
    q = np.arange(15.0, 30.0, 0.25)
    est = windowed_curvature(track, q, 1.5, imu_grade("tactical"))
    exact = window_curvature(g, q, 1.5)
    for key in ("vertical", "horizontal", "total"):
        assert est[key] == pytest.approx(exact[key], abs=1e-6)


def test_bend_list_of_a_known_geometry():
    d = 0.2
    g = pipe(
        Bend(10.0, 30 * DEG, 2.0, "h"),
        Bend(40.0, -5 * DEG, 50.0, "v"),
        Bend(120.0, 6 * DEG, 1.0, "h"),
        Bend(120.1, 4 * DEG, 1.0, "v"),  # overlaps the one before: one 3-D bend
        Bend(160.0, 0.5 * DEG, 5.0, "h"),  # under the listing angle
        diameter=d,
    )
    bends = truth_bends(g, 1 * DEG)
    assert [b.number for b in bends] == [1, 2, 3]
    b1, b2, b3 = bends
    arc = 30 * DEG * 2.0
    assert (b1.start_m, b1.end_m) == pytest.approx((10.0, 10.0 + arc + d))
    assert b1.apex_m == pytest.approx(10.0 + 0.5 * (arc + d))
    assert math.degrees(b1.angle) == pytest.approx(30.0, rel=1e-9)
    assert b1.radius == pytest.approx(2.0, rel=1e-9)
    assert (b1.direction, round(math.degrees(b1.plane), 6)) == ("right", 90.0)
    assert b1.source == "bend"
    lat, lon, alt = g.position(b1.apex_m)
    assert (b1.lat, b1.lon, b1.alt) == pytest.approx((float(lat), float(lon), float(alt)))
    assert (b2.direction, round(math.degrees(b2.plane), 6)) == ("over", 180.0)
    assert b2.radius == pytest.approx(50.0)
    assert math.degrees(b2.angle) == pytest.approx(5.0, rel=1e-9)
    # the 3-D bend: angle between the end tangents, the combined direction word
    t0, t1 = g.tangent_enu(np.array([b3.start_m, b3.end_m]))
    assert b3.angle == pytest.approx(math.acos(t0 @ t1), rel=1e-6)
    assert 6 * DEG < b3.angle < 10 * DEG
    assert b3.direction == "sag+right" and b3.source == "3-D"
    assert b3.start_m == pytest.approx(120.0) and b3.end_m > 120.1 + 4 * DEG
    assert 0.0 < math.degrees(b3.plane) < 90.0
    # min angle and max radius filters; a straight pipe has none
    assert len(truth_bends(g, 0.1 * DEG)) == 4
    assert [b.radius for b in truth_bends(g, 1 * DEG, max_radius=10.0)] == pytest.approx(
        [2.0, b3.radius])
    assert truth_bends(pipe(), 0.0) == []


def test_a_horizontal_bend_on_a_slope_turns_less_in_3d():
    g = pipe(Bend(10.0, 40 * DEG, 3.0, "h"), pitch0=10 * DEG)
    (b,) = truth_bends(g)
    assert b.angle == pytest.approx(2 * math.asin(math.cos(10 * DEG) * math.sin(20 * DEG)))
    assert b.radius == pytest.approx(3.0 / math.cos(10 * DEG))
    assert b.horizontal == pytest.approx(40 * DEG * math.cos(10 * DEG), rel=1e-6)
    assert b.vertical == pytest.approx(0.0, abs=1e-12)


def test_new_scenarios_and_their_truth():
    bt, ss = get_scenario("bends_test"), get_scenario("strain_span")
    assert bt.estimator_settings()["pipe_outer_diameter"] == pytest.approx(0.3239)
    assert ss.estimator_settings()["pipe_outer_diameter"] == pytest.approx(0.914)
    assert "pipe_outer_diameter" not in get_scenario("field10k").estimator_settings()
    bends = truth_bends(bt.build_geometry(), 0.0)
    assert len(bends) == 17 and sum(b.source == "3-D" for b in bends) == 1
    angles = sorted(round(math.degrees(b.angle), 3) for b in bends)
    assert angles[0] == 0.5 and angles[-1] == 10.0
    g = ss.build_geometry()
    s = np.arange(80.0, 100.0, 0.01)
    k = point_curvature(g, s)["total"]
    assert 1 / k.max() == pytest.approx(300.0, rel=1e-3)
    assert strain_pct(k.max(), 0.914) == pytest.approx(0.1523, abs=2e-4)


def test_truth_csvs_beside_the_bag(tmp_path):
    run = simulate("sag104", seed=1)
    out = tmp_path / "run.mcap"
    strain_path, bends_path = write_truth_products(out, run)
    assert (strain_path, bends_path) == truth_product_paths(out)
    assert strain_path.name == "run_truth_strain.csv" and bends_path.name == "run_truth_bends.csv"
    with open(strain_path, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == STRAIN_COLUMNS
    header = ("distance_m,latitude_deg,longitude_deg,altitude_m,curvature_vertical_per_m,"
              "curvature_horizontal_per_m,curvature_total_per_m,curvature_plane_deg,strain_pct,"
              "sigma_strain_pct")  # INTERFACES.md
    assert ",".join(rows[0][:10]) == header
    d = np.array([[float(x) for x in r] for r in rows[1:]])
    assert d[0, 0] == 0.0 and d[-1, 0] == pytest.approx(103.5) and np.all(np.diff(d[:, 0]) == 0.5)
    assert np.all(d[:, 9] == 0.0) and np.all(np.diff(d[:, 11]) >= 0)  # sigma 0, time increasing
    # strain is the window-mean curvature x D / 2 (bore 0.2 m: no outer diameter given)
    assert d[:, 8] == pytest.approx(d[:, 6] * 0.1 * 100, abs=1e-6)
    with open(bends_path, newline="") as f:
        brows = list(csv.DictReader(f))
    assert list(brows[0]) == BEND_COLUMNS
    assert [r["direction"] for r in brows] == ["over", "sag", "over"]  # the three sag lobes
