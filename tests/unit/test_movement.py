"""Run-to-run movement (products/movement.py, sim/movement.py, pipe-nav compare): zero through an
unmoved pipe, an injected 10 cm movement over 50 m found with its size, the outputs."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.cli import main
from pipe_nav_core.bench.runs import score_movement, smoothed
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io.movement_files import (
    MOVEMENT_COLUMNS,
    plot_movement,
    write_movement_csv,
    write_movement_geojson,
)
from pipe_nav_core.products.movement import chainage_map, compare_runs
from pipe_nav_core.sim import get_scenario
from pipe_nav_core.sim.movement import GroundMovement, moved_scenario, true_displacement

SCN = get_scenario("demo")  # 300 m, markers every 100 m, magnetometer: welds every 12 m
CFG = NavConfig.from_dict(SCN.estimator_settings())
MOVE = [GroundMovement(140.0, 50.0, lateral=0.10, settlement=0.0)]  # between two markers


@pytest.fixture(scope="module")
def runs():
    run_a, a = smoothed(SCN, 1, CFG)
    _, b = smoothed(SCN, 2, CFG)  # another run through the same, unmoved pipe
    _, c = smoothed(moved_scenario(SCN, MOVE), 3, CFG)  # after the ground moved
    return run_a, a, b, c


def test_the_displacement_field_is_the_injected_bell():
    g = SCN.build_geometry()
    lat, lon, h = g.position(0.0)
    from pipe_nav_core.types import Datum

    datum = Datum(float(lat), float(lon), float(h))
    s = np.array([100.0, 140.0, 165.0, 190.0, 250.0])
    d = true_displacement(SCN, MOVE, s, datum)
    assert np.linalg.norm(d[2]) == pytest.approx(0.10, abs=1e-3)  # the peak, horizontal
    assert abs(d[2, 2]) < 1e-3
    assert np.all(np.linalg.norm(d[[0, 1]], axis=1) < 1e-9)  # nothing moved before it
    assert np.linalg.norm(d[4]) < 0.005  # after it: the axial take-up of a few mm only
    axis = g.tangent_enu(165.0)
    assert abs(float(d[2] @ axis)) < 0.005  # lateral: across the pipe
    assert float(np.cross(axis, d[2])[2]) < 0  # to the right looking downstream
    sag = true_displacement(SCN, [GroundMovement(20.0, 40.0, 0.0, 0.05)], [40.0], datum)
    assert sag[0, 2] == pytest.approx(-0.05, abs=1e-3)
    with pytest.raises(ValueError, match="past the pipe's end"):
        moved_scenario(SCN, [GroundMovement(280.0, 50.0)])


def test_two_runs_through_an_unmoved_pipe_agree_within_their_sigmas(runs):
    _, a, b, _ = runs
    rep = compare_runs(a, b, CFG)
    assert rep.weld_pairs >= 20 and not rep.notes
    pts = rep.points
    assert not any(p.significant for p in pts)
    z = np.array([p.d_enu / p.sigma_enu for p in pts])
    assert np.abs(z).max() < 3.0
    # under 5 cm but where the sigma says more (the weld in the 45 deg elbow at 60 m)
    assert all(p.magnitude < max(0.05, 3.0 * float(np.linalg.norm(p.sigma_enu))) for p in pts)
    assert sum(p.magnitude >= 0.05 for p in pts) <= 1


def test_a_10_cm_movement_over_50_m_is_found_with_its_size(runs):
    run_a, a, _, c = runs
    rep = compare_runs(a, c, CFG)
    row = score_movement(rep, run_a, a, SCN, MOVE)
    assert row["found"], rep.intervals
    assert row["true_peak_m"] > 0.08
    assert abs(row["peak_size_error_m"]) < 0.02
    # no false movement elsewhere
    elsewhere = [p for p in rep.points if not 140.0 < p.distance < 190.0]
    assert not any(p.significant for p in elsewhere)
    assert sum(p.magnitude >= 0.05 for p in elsewhere) <= 1  # the weld in the elbow at 60 m
    (iv,) = rep.intervals
    assert 140.0 < iv.start_m <= iv.peak_m <= iv.end_m < 190.0
    # the pipe bent there: the horizontal curvature changed most inside the moved stretch
    inside = [p for p in rep.points if 140.0 < p.distance < 190.0]
    outside = [p for p in rep.points if 70.0 < p.distance < 130.0 or 200 < p.distance < 250]
    assert max(abs(p.d_curvature_horizontal) for p in inside) > 2 * max(
        abs(p.d_curvature_horizontal) for p in outside
    )


def test_a_stricter_threshold_hides_it_and_bad_settings_are_refused(runs):
    _, a, _, c = runs
    assert not compare_runs(a, c, CFG, threshold=0.5).intervals
    with pytest.raises(ValueError, match="threshold"):
        compare_runs(a, c, CFG, threshold=-1.0)
    with pytest.raises(ValueError, match="n_sigma"):
        compare_runs(a, c, CFG, n_sigma=0.0)


def test_without_welds_the_bends_align_the_runs(runs):
    _, a, _, c = runs
    rep = compare_runs(replace(a, welds=[]), replace(c, welds=[]), CFG)
    assert rep.weld_pairs == 0 and rep.bend_pairs >= 1
    assert all(p.anchor == "bend" for p in rep.points)
    assert any("bends" in n for n in rep.notes)


def test_chainage_map_is_piecewise_linear_and_continued_at_scale_one():
    f = chainage_map(np.array([10.0, 20.0]), np.array([11.0, 22.0]))
    assert f(np.array([0.0, 15.0, 30.0])) == pytest.approx([1.0, 16.5, 32.0])


def test_the_movement_files(runs, tmp_path: Path):
    _, a, _, c = runs
    rep = compare_runs(a, c, CFG)
    out = tmp_path / "MOVEMENT.csv"
    write_movement_csv(out, rep)
    write_movement_geojson(tmp_path / "MOVEMENT.geojson", rep)
    plot_movement(tmp_path / "MOVEMENT.png", rep)
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == MOVEMENT_COLUMNS
    documented = "weld,distance_m,latitude_deg,longitude_deg,altitude_m,d_east_m,d_north_m,d_up_m"
    documented += ",sigma_d_east_m,sigma_d_north_m,sigma_d_up_m,significant"
    assert MOVEMENT_COLUMNS[:12] == documented.split(",")  # noqa: SIM905
    assert len(rows) == len(rep.points)
    assert sum(int(r["significant"]) for r in rows) == sum(p.significant for p in rep.points)
    assert float(rows[3]["d_east_m"]) == pytest.approx(rep.points[3].d_enu[0], abs=1e-4)
    assert len(rows[0]["latitude_deg"].split(".")[1]) == 9
    doc = json.loads((tmp_path / "MOVEMENT.geojson").read_text())
    kinds = [f["properties"]["kind"] for f in doc["features"]]
    assert kinds.count("movement_point") == len(rep.points)
    assert kinds.count("movement_interval") == len(rep.intervals) == 1
    lon, lat, _ = doc["features"][0]["geometry"]["coordinates"]
    assert lat == pytest.approx(math.degrees(rep.points[0].lat), abs=1e-9)
    assert (tmp_path / "MOVEMENT.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_pipe_nav_compare_on_smoothed_bags(tmp_path: Path, capsys):
    """End to end: two bags simulated, smoothed by pipe-nav smooth, compared."""
    from pipe_nav_core.io import write_sensor_bag
    from pipe_nav_core.sim import simulate

    short = SCN.with_length(150.0)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({k: list(v) if isinstance(v, tuple) else v
                               for k, v in short.estimator_settings().items()}))  # fmt: skip
    move = [GroundMovement(60.0, 50.0, lateral=0.15, settlement=0.0)]
    for name, scn, seed in (("a", short, 1), ("b", moved_scenario(short, move), 2)):
        write_sensor_bag(str(tmp_path / f"{name}.mcap"), simulate(scn, seed).log)
        smoothed_bag = str(tmp_path / f"{name}_smoothed.mcap")
        assert main(["smooth", str(tmp_path / f"{name}.mcap"), "--out", smoothed_bag,
                     "--config", str(cfg)]) == 0  # fmt: skip
    capsys.readouterr()
    out = tmp_path / "MOVEMENT.csv"
    assert main(["compare", str(tmp_path / "a_smoothed.mcap"), str(tmp_path / "b_smoothed.mcap"),
                 "--out", str(out), "--workers", "1"]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "1 movement interval(s)" in text, text
    assert (tmp_path / "MOVEMENT.geojson").exists() and (tmp_path / "MOVEMENT.png").exists()
    with out.open() as f:
        rows = list(csv.DictReader(f))
    peak = max(rows, key=lambda r: float(r["d_m"]))
    assert 60.0 < float(peak["distance_m"]) < 110.0 and peak["significant"] == "1"
    assert float(peak["d_m"]) == pytest.approx(0.15, abs=0.03)
    # a file that is not a smoothed bag: one line naming it, exit 2
    assert main(["compare", str(cfg), str(tmp_path / "b_smoothed.mcap"), "--out",
                 str(tmp_path / "M2.csv"), "--workers", "1"]) == 2  # fmt: skip
    assert str(cfg) in capsys.readouterr().err
