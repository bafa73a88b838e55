"""Curvature, bends and strain (products/) on pipes of known, closed-form geometry."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.config import NavConfig
from pipe_nav_core.geo.attitude import quat_from_euler
from pipe_nav_core.geo.earth import radii
from pipe_nav_core.io.products_csv import write_bends_csv, write_strain_csv
from pipe_nav_core.products import (
    integrity_report,
    read_bends_reference,
    strain_features,
)
from pipe_nav_core.types import Trajectory

DEG = math.pi / 180.0
STEP = 0.01  # m between samples of the synthetic trajectories


def pipe(azimuth, pitch, length: float, speed: float = 1.5) -> Trajectory:
    """A noise-free trajectory along a pipe given its azimuth(s) and pitch(s) (rad) as
    functions of the chainage s (m): positions integrated from the axis."""
    s = np.arange(0.0, length, STEP)
    az, th = azimuth(s), pitch(s)
    e = np.cumsum(np.cos(th) * np.sin(az)) * STEP
    n = np.cumsum(np.cos(th) * np.cos(az)) * STEP
    u = np.cumsum(np.sin(th)) * STEP
    lat0 = 0.7
    rm, rn = radii(lat0)
    return Trajectory(
        t=s / speed, lat=lat0 + n / rm, lon=e / (rn * math.cos(lat0)), h=u,
        vel_n=np.zeros((len(s), 3)), quat_nb=quat_from_euler(0 * s, th, az), distance=s,
    )  # fmt: skip


def arc(start: float, angle: float, radius: float):
    """An angle(s) function: straight, then a circular arc of ``radius`` turning ``angle``."""
    length = abs(angle) * radius
    return lambda s: np.clip((s - start) / length, 0.0, 1.0) * angle


CFG = NavConfig(imu_grade="tactical", pipe_outer_diameter=0.3, curvature_window=1.0)


def test_circular_horizontal_arc_against_its_closed_form():
    traj = pipe(arc(100.0, 30 * DEG, 60.0), lambda s: 0 * s, 250.0)
    rep = integrity_report(traj, CFG)
    p = rep.profile
    inside = (p.distance > 101.0) & (p.distance < 100.0 + 60.0 * 30 * DEG - 1.0)
    np.testing.assert_allclose(p.total[inside], 1 / 60.0, rtol=1e-4)
    np.testing.assert_allclose(p.horizontal[inside], 1 / 60.0, rtol=1e-4)
    assert np.abs(p.vertical[inside]).max() < 1e-6
    np.testing.assert_allclose(np.degrees(p.plane[inside]), 90.0, atol=1e-3)
    assert np.all(p.total[p.distance < 99.0] < 1e-9)
    np.testing.assert_allclose(rep.strain_pct[inside], 0.15 / 60.0 * 100.0, rtol=1e-4)
    (b,) = rep.bends
    assert b.direction == "right" and b.kind == "elastic"  # 60 m = 200 D
    assert abs(b.angle - 30 * DEG) < 1e-4
    assert abs(b.radius - 60.0) / 60.0 < 1e-3
    assert abs(b.apex_m - (100.0 + 30.0 * 30 * DEG)) < 0.05
    assert b.sigma_angle > 0 and b.sigma_radius > 0


def test_vertical_arcs_bend_up_and_down():
    # a sag bottom (bending upward) then a crest, each 45 deg at 3 outer diameters (0.9 m)
    up, down = arc(50.0, 45 * DEG, 0.9), arc(100.0, -45 * DEG, 0.9)
    traj = pipe(lambda s: 0 * s, lambda s: up(s) + down(s), 160.0)
    rep = integrity_report(traj, CFG)
    assert [b.direction for b in rep.bends] == ["sag", "over"]
    assert [b.kind for b in rep.bends] == ["induction", "induction"]
    for b in rep.bends:
        assert abs(b.angle - 45 * DEG) < 1e-4
        assert abs(b.radius_d - 3.0) / 3.0 < 0.05  # resolved though shorter than the window
    np.testing.assert_allclose(np.degrees(rep.profile.plane[rep.profile.distance == 50.0]), 0.0,
                               atol=1e-6)  # fmt: skip


def test_helix_has_its_closed_form_curvature():
    r, rise = 30.0, 10 * DEG  # a helix about a vertical axis: constant pitch, turning azimuth
    traj = pipe(lambda s: s * math.cos(rise) / r, lambda s: 0 * s + rise, 120.0)
    p = integrity_report(traj, CFG).profile
    mid = (p.distance > 5) & (p.distance < 115)
    np.testing.assert_allclose(p.total[mid], math.cos(rise) ** 2 / r, rtol=1e-4)
    np.testing.assert_allclose(p.horizontal[mid], math.cos(rise) ** 2 / r, rtol=1e-4)
    assert np.abs(p.vertical[mid]).max() < 1e-6


def test_a_straight_pipe_has_no_bend_and_no_strain_feature():
    traj = pipe(lambda s: 0 * s + 1.0, lambda s: 0 * s + 0.05, 500.0)
    rep = integrity_report(traj, CFG)
    assert rep.bends == [] and rep.features == []
    assert rep.profile.total.max() < 1e-9


def test_an_s_bend_is_two_bends_and_small_ones_are_not_listed():
    right, left = arc(50.0, 8 * DEG, 30.0), arc(50.0 + 30 * 8 * DEG, -8 * DEG, 30.0)
    small = arc(200.0, 0.5 * DEG, 100.0)  # under bend_min_angle (1 deg)
    traj = pipe(lambda s: right(s) + left(s) + small(s), lambda s: 0 * s, 300.0)
    rep = integrity_report(traj, CFG)
    assert [b.direction for b in rep.bends] == ["right", "left"]
    assert [b.number for b in rep.bends] == [1, 2]
    for b in rep.bends:
        assert abs(b.angle - 8 * DEG) < 1e-3


@pytest.mark.parametrize("offset", [0.0, 0.15, 0.35, 0.45])
def test_a_bend_shorter_than_the_row_spacing_reaches_its_apex_and_peak(offset: float):
    """Bends of 0.05 to 0.5 m of arc (field line induction bends of 1 to 7 deg) on 0.5 m rows
    with a 0.6 m window: over the threshold at one row, their apex, found on a finer grid, lay
    up to 0.17 m beyond it (start_m = end_m = 50.5, apex_m 50.41), and the strain features'
    peaks likewise: start_m <= apex_m (peak_m) <= end_m, wherever the bend falls between the
    rows."""
    cfg = NavConfig(imu_grade="tactical", pipe_outer_diameter=0.219, curvature_window=0.6)
    for angle_deg, radius in ((3.0, 1.5), (1.3, 3.5), (6.9, 1.0), (45.0, 0.7)):
        turn = arc(50.0 + offset, angle_deg * DEG, radius)
        rep = integrity_report(pipe(turn, lambda s: 0 * s, 100.0), cfg)
        (b,) = rep.bends
        assert b.start_m <= b.apex_m <= b.end_m, (angle_deg, b.start_m, b.apex_m, b.end_m)
        assert rep.features and all(f.bend == 1 for f in rep.features)
        for f in rep.features:  # the strain stretches likewise reach their peaks
            assert f.start_m <= f.peak_m <= f.end_m, (angle_deg, f.start_m, f.peak_m, f.end_m)
        centre = 50.0 + offset + 0.5 * radius * angle_deg * DEG
        assert abs(b.apex_m - centre) < 0.1


def test_a_combined_bend_is_named_by_both_planes():
    turn, dip = arc(50.0, 10 * DEG, 20.0), arc(50.0, -6 * DEG, 20.0 * 10 / 6)
    rep = integrity_report(pipe(turn, dip, 150.0), CFG)
    (b,) = rep.bends
    assert b.direction == "over+right"
    assert 90.0 < math.degrees(b.plane) < 180.0


def test_the_summary_tells_the_strain_of_a_bend_from_the_strain_outside_bends():
    """A 3 D induction bend (shorter than the 1 m window: 45 deg over it, 11.8 % in a 0.3 m
    pipe) and, below bend_min_angle and so not a listed bend, a 0.8 deg arc of 200 m radius
    (0.075 %): the largest strain is the bend's, named; the largest outside bends is the arc's."""
    elbow, small = arc(50.0, 45 * DEG, 0.9), arc(150.0, 0.8 * DEG, 200.0)
    rep = integrity_report(pipe(lambda s: elbow(s) + small(s), lambda s: 0 * s, 250.0), CFG)
    (b,) = rep.bends
    s = rep.summary()
    assert s["max_strain_bend"] == b.number == 1
    assert s["max_strain_pct"] == rep.strain_pct.max() and abs(s["max_strain_pct"] - 11.78) < 0.1
    assert abs(s["max_strain_outside_bends_pct"] - 0.15 / 200.0 * 100.0) < 1e-3
    straight = integrity_report(pipe(lambda s: 0 * s, lambda s: 0 * s, 50.0), CFG).summary()
    assert straight["max_strain_bend"] == 0
    assert straight["max_strain_outside_bends_pct"] == straight["max_strain_pct"] < 1e-6


def test_strain_features_and_the_as_built_reference(tmp_path: Path):
    # a 200 m radius stretch in a 0.3 m pipe: strain 0.075 %; a 60 m one: 0.25 %
    a, b = arc(50.0, 6 * DEG, 200.0), arc(150.0, 10 * DEG, 60.0)
    rep = integrity_report(pipe(lambda s: a(s) + b(s), lambda s: 0 * s, 260.0), CFG)
    assert [f.threshold_pct for f in rep.features] == [0.125, 0.2]  # only the tight one
    ref = tmp_path / "asbuilt.csv"
    ref.write_text("start_m,end_m,name\n0,10,launch\n")
    feats = strain_features(rep.profile, 0.3, (0.125,), rep.bends, read_bends_reference(ref))
    assert len(feats) == 1
    f = feats[0]
    assert f.construction is False and f.bend == 2  # explained by bend 2, not as-built
    assert abs(f.peak_pct - 0.25) < 1e-3
    assert f.start_m > 150.0 - 1.0 and f.end_m < 150.0 + 60.0 * 10 * DEG + 1.0
    ref.write_text("start_m,end_m\n140,170\n")
    feats = strain_features(rep.profile, 0.3, (0.125,), (), read_bends_reference(ref))
    assert feats[0].construction is True and feats[0].bend == 0


def test_bends_reference_errors_name_the_file_and_line(tmp_path: Path):
    bad = tmp_path / "ref.csv"
    bad.write_text("start_m,end_m\n1,2\nx,3\n")
    with pytest.raises(ValueError, match=r"ref.csv:3"):
        read_bends_reference(bad)
    bad.write_text("from,to\n1,2\n")
    with pytest.raises(ValueError, match="lacks end_m, start_m"):
        read_bends_reference(bad)


def test_csv_headers_are_the_documented_ones(tmp_path: Path):
    rep = integrity_report(pipe(arc(20.0, 20 * DEG, 5.0), lambda s: 0 * s, 60.0), CFG)
    write_strain_csv(tmp_path / "s.csv", rep.profile, rep.strain_pct, rep.sigma_strain_pct)
    write_bends_csv(tmp_path / "b.csv", rep.bends)
    strain = (tmp_path / "s.csv").read_text().splitlines()
    bends = (tmp_path / "b.csv").read_text().splitlines()
    assert strain[0].startswith(
        "distance_m,latitude_deg,longitude_deg,altitude_m,curvature_vertical_per_m,"
        "curvature_horizontal_per_m,curvature_total_per_m,curvature_plane_deg,strain_pct,"
        "sigma_strain_pct"
    )
    assert bends[0].startswith(
        "bend,start_m,apex_m,end_m,latitude_deg,longitude_deg,altitude_m,angle_deg,"
        "sigma_angle_deg,radius_m,radius_d,plane_deg,direction,class"
    )
    assert len(strain) == 1 + len(rep.profile) and len(bends) == 2
    row = bends[1].split(",")
    assert row[0] == "1" and abs(float(row[7]) - 20.0) < 1e-3 and row[12] == "right"
    assert len(row[4].split(".")[1]) == 9  # latitude to 0.1 mm


def test_writers_refuse_non_finite_values(tmp_path: Path):
    rep = integrity_report(pipe(arc(20.0, 20 * DEG, 5.0), lambda s: 0 * s, 60.0), CFG)
    bad = rep.strain_pct.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        write_strain_csv(tmp_path / "s.csv", rep.profile, bad, rep.sigma_strain_pct)
    assert not (tmp_path / "s.csv").exists()


def test_the_axis_track_built_in_batches_is_the_same(monkeypatch):
    """At field scale the axis track is built a batch of points at a time (bounded memory):
    batches of a few points give the track of one batch, bit for bit, sigmas included."""
    from pipe_nav_core.products import curvature

    from pipe_nav_core import batched

    traj = pipe(lambda s: arc(5.0, 30 * DEG, 10.0)(s), lambda s: arc(12.0, -5 * DEG, 40.0)(s), 30.0)
    traj.sigma_enu = np.random.default_rng(0).random((len(traj.t), 3))
    whole = curvature.axis_track(traj)
    monkeypatch.setattr(batched, "BATCH", 7)
    batched = curvature.axis_track(traj)
    for name in whole.__dataclass_fields__:
        assert getattr(batched, name).tobytes() == getattr(whole, name).tobytes(), name


def test_apexes_and_peaks_found_together_are_those_found_one_by_one():
    """The bends' apexes and the strain features' peaks are refined for every stretch in one
    call of windowed_curvature (a window per point): the same, bit for bit, as one stretch at
    a time, on a pipe whose bends differ in length (so their grids, windows and rounds do)."""
    from pipe_nav_core.model.sensors import imu_grade
    from pipe_nav_core.products import bends, curvature, strain

    turns = [arc(20.0, 12 * DEG, 8.0), arc(60.0, -3 * DEG, 2.0), arc(90.0, 40 * DEG, 1.5),
             arc(130.0, 5 * DEG, 60.0)]  # fmt: skip
    traj = pipe(lambda s: sum(t(s) for t in turns), lambda s: arc(40.0, 4 * DEG, 30.0)(s), 200.0)
    spec = imu_grade("tactical")
    track = curvature.axis_track(traj)
    profile = curvature.curvature_profile(traj, spec, window=0.6, track=track)
    stretches = bends._stretches(profile, 1.0 / CFG.bend_threshold_radius)
    assert len(stretches) >= 4
    floor = 4.0 * float(np.median(np.diff(track.arc)))
    together = bends._apexes(profile, track, spec, stretches, floor)
    assert together == [bends._apexes(profile, track, spec, [s], floor)[0] for s in stretches]
    assert all(a is not None for a in together)
    rows = [a + int(np.argmax(profile.total[a : b + 1])) for a, b in stretches]
    peaks = strain._peaks(profile, 0.3, track, spec, rows)
    assert peaks == [strain._peaks(profile, 0.3, track, spec, [r])[0] for r in rows]
    arcs = np.linspace(5.0, 150.0, 40)
    windows = np.linspace(0.3, 2.0, 40)
    each = [curvature.windowed_curvature(track, arcs[i : i + 1], windows[i], spec)
            for i in range(40)]  # fmt: skip
    per_point = curvature.windowed_curvature(track, arcs, windows, spec)
    for name, values in per_point.items():
        assert values.tobytes() == np.concatenate([e[name] for e in each]).tobytes(), name
