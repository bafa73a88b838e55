"""Marker CSV, centreline CSV, chainage resampling, GeoJSON, KML, atomic writes."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from pipe_nav_core.geo.attitude import dcm_from_quat, euler_from_dcm
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.io import (
    CENTRELINE_COLUMNS,
    MarkerCsvError,
    OutputIsInputError,
    atomic_path,
    atomic_write,
    ensure_not_input,
    interpolate_trajectory,
    merge_markers,
    read_centreline_csv,
    read_markers_csv,
    resample_by_chainage,
    write_centreline_csv,
    write_geojson,
    write_kml,
    write_markers_csv,
)
from pipe_nav_core.io.atomic import all_or_none
from pipe_nav_core.io.gis import to_geojson
from pipe_nav_core.types import Marker
from test_io_support import DATUM, make_traj

MK = [
    Marker("launch", 10.0, math.radians(52.1), math.radians(5.2), 40.0, (0.02, 0.02, 0.03)),
    Marker("agm_01", 60.5, math.radians(52.1003), math.radians(5.2008), 39.5, (0.05, 0.05, 0.1)),
    Marker(
        "receive", 190.25, math.radians(52.101), math.radians(5.2021), 38.25, (0.02, 0.02, 0.02)
    ),
]


# ----------------------------------------------------------------------------- markers CSV


def test_marker_csv_round_trip_and_header(tmp_path):
    p = tmp_path / "m.csv"
    write_markers_csv(p, list(reversed(MK)))
    lines = p.read_text().splitlines()
    assert lines[0] == "name,time_s,latitude_deg,longitude_deg,altitude_m,sigma_h_m,sigma_v_m"
    assert lines[1].startswith("launch,10.000000000,52.100000000,5.200000000,40.0000,0.0200,")
    back = read_markers_csv(p)
    assert [m.name for m in back] == ["launch", "agm_01", "receive"]
    for a, b in zip(MK, back, strict=True):
        assert (a.name, a.t, a.alt) == (b.name, b.t, b.alt)
        assert abs(a.lat - b.lat) < 1e-11 and abs(a.lon - b.lon) < 1e-11  # 9 decimals of deg
        np.testing.assert_allclose(a.sigma_enu, b.sigma_enu)


def test_marker_csv_tolerant_layout_and_defaults(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text(
        "# surveyed 2024-05-01\n"
        "time_s,name,latitude_deg,longitude_deg,altitude_m,sigma_h_m,sigma_v_m,comment\n"
        "\n"
        "12.5,agm_a,52.1,5.2,40,,,in the field\n"
        "2.5,agm_b,52.0,5.1,41,0.1,0.2,\n"
    )
    ms = read_markers_csv(p)
    assert [m.name for m in ms] == ["agm_b", "agm_a"]  # time order
    assert ms[1].sigma_enu == (0.05, 0.05, 0.05)
    assert ms[0].sigma_enu == (0.1, 0.1, 0.2)
    assert ms[0].lat == pytest.approx(math.radians(52.0))


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("name,time_s,latitude_deg\n", "missing column"),
        (
            "name,time_s,latitude_deg,longitude_deg,altitude_m\na,1,52,x,3\n",
            ":2: longitude_deg 'x'",
        ),
        ("name,time_s,latitude_deg,longitude_deg,altitude_m\na,1,52,5,3\na,2,52,5,3\n", "twice"),
        ("name,time_s,latitude_deg,longitude_deg,altitude_m\na,1,95,5,3\n", "out of range"),
        ("", "empty"),
    ],
)
def test_marker_csv_errors_name_file_and_line(tmp_path, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(MarkerCsvError, match=match):
        read_markers_csv(p)


def test_merge_markers_adds_and_replaces():
    bag = [MK[0], MK[1]]
    moved = Marker("agm_01", 61.0, MK[1].lat + 1e-7, MK[1].lon, 39.0, (0.01, 0.01, 0.01))
    new = Marker("agm_02", 100.0, MK[2].lat, MK[2].lon, 38.0)
    out = merge_markers(bag, [new, moved])
    assert [m.name for m in out] == ["launch", "agm_01", "agm_02"]
    assert out[1] is moved
    assert merge_markers(bag, []) == bag
    assert merge_markers([], [new]) == [new]


# ----------------------------------------------------------------------------- resampling


def test_resample_by_chainage_spacing_stops_and_marker_rows():
    traj = make_traj(n=2001, seconds=200.0)  # 1 m/s, stop between 100 and 110 s
    marker_times = [37.123, 105.0, 150.0004, 500.0]  # 500 s is outside the run
    r = resample_by_chainage(traj, 0.5, marker_times)
    assert np.all(np.diff(r.t) > 0)
    assert r.t[0] == traj.t[0] and r.t[-1] == traj.t[-1]
    for mt in marker_times[:3]:
        assert np.any(r.t == mt)
    grid = ~np.isin(r.t, marker_times + [traj.t[0], traj.t[-1]])
    dg = r.distance[grid]
    np.testing.assert_allclose(dg, np.round(dg / 0.5) * 0.5, atol=1e-9)
    np.testing.assert_allclose(np.diff(dg), 0.5, atol=1e-9)
    # multiples of 0.5 m from 0 (the first sample, not counted in ``grid``) to the end
    assert grid.sum() == math.floor(traj.distance[-1] / 0.5)
    # during the stop there is only the marker row, no pile of grid rows
    in_stop = (r.t > 100.5) & (r.t < 109.5)
    assert r.t[in_stop].tolist() == [105.0]
    # interpolated values are consistent with the original at a sample time
    k = 333
    one = interpolate_trajectory(traj, [traj.t[k]])
    assert one.lat[0] == pytest.approx(traj.lat[k], abs=1e-15)
    np.testing.assert_allclose(one.quat_nb[0], traj.quat_nb[k], atol=1e-12)


def test_resample_handles_backward_creep():
    traj = make_traj(n=201, seconds=20.0)
    d = traj.distance.copy()
    d[100:110] -= np.linspace(0, 0.3, 10)  # the wheel rolls back a little
    traj.distance = d
    r = resample_by_chainage(traj, 0.25)
    assert np.all(np.diff(r.t) > 0)
    assert len(r.t) == len(np.unique(r.t))


def test_slerp_midpoint():
    from pipe_nav_core.geo.attitude import quat_from_euler

    t = np.array([0.0, 2.0])
    q = quat_from_euler([0.0, 0.0], [0.0, 0.0], [math.radians(10.0), math.radians(350.0)])
    traj = make_traj(n=2)
    traj.t, traj.quat_nb = t, q
    mid = interpolate_trajectory(traj, [1.0])
    _, _, az = euler_from_dcm(dcm_from_quat(mid.quat_nb[0]))
    assert math.degrees(float(az)) == pytest.approx(0.0, abs=1e-9) or math.degrees(
        float(az)
    ) == pytest.approx(360.0, abs=1e-9)  # the short way round through north


# ----------------------------------------------------------------------------- centreline CSV


def test_centreline_csv_header_and_round_trip(tmp_path):
    traj = resample_by_chainage(make_traj(n=501, seconds=50.0), 0.5)
    p = tmp_path / "c.csv"
    write_centreline_csv(p, traj, DATUM)
    text = p.read_text()
    assert text.splitlines()[0] == (
        "time_s,distance_m,latitude_deg,longitude_deg,altitude_m,east_m,north_m,up_m,"
        "roll_deg,pitch_deg,azimuth_deg,sigma_east_m,sigma_north_m,sigma_up_m"
    )
    assert text.splitlines()[0].split(",") == CENTRELINE_COLUMNS
    assert len(text.splitlines()) == len(traj.t) + 1
    row = text.splitlines()[5].split(",")
    assert len(row[2].split(".")[1]) == 9 and len(row[5].split(".")[1]) == 4
    back, datum = read_centreline_csv(p)
    np.testing.assert_allclose(back.t, traj.t, atol=1e-9)
    np.testing.assert_allclose(back.distance, traj.distance, atol=1e-4)
    np.testing.assert_allclose(back.lat, traj.lat, atol=1e-11)
    np.testing.assert_allclose(back.h, traj.h, atol=1e-4)
    np.testing.assert_allclose(back.sigma_enu, traj.sigma_enu, atol=1e-4)
    # attitude survives (degrees with 6 decimals)
    dq = np.abs(np.sum(back.quat_nb * traj.quat_nb, axis=1))
    assert np.all(dq > 1 - 1e-10)
    # the datum comes back from the ENU and geodetic columns
    assert datum.lat == pytest.approx(DATUM.lat, abs=1e-10)
    assert datum.lon == pytest.approx(DATUM.lon, abs=1e-10)
    assert datum.alt == pytest.approx(DATUM.alt, abs=1e-3)
    enu = geodetic_to_enu(back.lat, back.lon, back.h, DATUM.lat, DATUM.lon, DATUM.alt)
    np.testing.assert_allclose(back.vel_n[1:-1, 0], np.gradient(enu[:, 0], back.t)[1:-1], atol=1e-3)


def test_centreline_csv_without_sigma_and_azimuth_range(tmp_path):
    traj = make_traj(n=101, seconds=10.0, with_sigma=False)
    p = tmp_path / "c.csv"
    write_centreline_csv(p, traj, DATUM)
    rows = [r.split(",") for r in p.read_text().splitlines()[1:]]
    assert all(r[11:] == ["", "", ""] for r in rows)
    az = np.array([float(r[10]) for r in rows])
    assert np.all((az >= 0.0) & (az < 360.0))
    back, _ = read_centreline_csv(p)
    assert back.sigma_enu is None


# ----------------------------------------------------------------------------- GIS


def test_geojson_linestring_and_points(tmp_path):
    traj = make_traj(n=101, seconds=10.0)
    p = tmp_path / "c.geojson"
    write_geojson(p, traj, MK)
    doc = json.loads(p.read_text())
    assert doc["type"] == "FeatureCollection"
    line = doc["features"][0]["geometry"]
    assert line["type"] == "LineString" and len(line["coordinates"]) == 101
    lon, lat, alt = line["coordinates"][17]
    assert lon == pytest.approx(math.degrees(traj.lon[17]), abs=1e-9)  # [lon, lat, alt]
    assert lat == pytest.approx(math.degrees(traj.lat[17]), abs=1e-9)
    assert alt == pytest.approx(traj.h[17], abs=1e-4)
    pts = [f for f in doc["features"] if f["geometry"]["type"] == "Point"]
    assert [f["properties"]["name"] for f in pts] == ["launch", "agm_01", "receive"]
    # the text json.dump streams, written at once (json.dumps: its compiled encoder)
    streamed = io.StringIO()
    json.dump(to_geojson(traj, MK, name="c"), streamed, separators=(",", ":"), allow_nan=False)
    assert p.read_text() == streamed.getvalue() + "\n"
    assert pts[1]["geometry"]["coordinates"][:2] == [
        pytest.approx(5.2008, abs=1e-9),
        pytest.approx(52.1003, abs=1e-9),
    ]


def test_kml_parses_with_absolute_altitudes(tmp_path):
    traj = make_traj(n=51, seconds=5.0)
    p = tmp_path / "c.kml"
    write_kml(p, traj, MK)
    root = ET.parse(p).getroot()
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    ls = root.find(".//k:LineString", ns)
    assert ls.find("k:altitudeMode", ns).text == "absolute"
    coords = ls.find("k:coordinates", ns).text.split()
    assert len(coords) == 51
    lon, lat, alt = (float(x) for x in coords[3].split(","))
    assert lon == pytest.approx(math.degrees(traj.lon[3]), abs=1e-9)
    assert lat == pytest.approx(math.degrees(traj.lat[3]), abs=1e-9)
    names = [e.text for e in root.findall(".//k:Placemark/k:name", ns)]
    assert names == ["c", "launch", "agm_01", "receive"]
    assert "ellipsoid" in root.find(".//k:description", ns).text


def test_kml_names_with_markup_characters_survive(tmp_path):
    """Marker names with &, < and > are escaped as xml.sax.saxutils escapes them, and parse
    back to themselves."""
    from xml.sax.saxutils import escape

    from pipe_nav_core.io import gis

    odd = "a&b <c> d&amp;"
    assert gis._escape(odd) == escape(odd)
    traj = make_traj(n=11, seconds=1.0)
    mk = [dataclasses.replace(MK[0], name=odd), *MK[1:]]
    p = tmp_path / "odd.kml"
    write_kml(p, traj, mk)
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    names = [e.text for e in ET.parse(p).getroot().findall(".//k:Placemark/k:name", ns)]
    assert odd in names


# ----------------------------------------------------------------------------- atomic


def test_atomic_write_leaves_nothing_on_error(tmp_path):
    p = tmp_path / "out.txt"
    with pytest.raises(RuntimeError), atomic_write(p) as f:
        f.write("half a file")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    p.write_text("old content")
    with pytest.raises(KeyboardInterrupt), atomic_write(p, "wb") as f:
        f.write(b"new")
        raise KeyboardInterrupt
    assert p.read_text() == "old content"
    assert list(tmp_path.iterdir()) == [p]


def test_a_signal_as_the_temporary_file_is_made_leaves_nothing(tmp_path, monkeypatch):
    """Python runs a signal handler as a system call returns: SIGTERM (raised as an interrupt)
    can land once os.open has made the temporary file and before anything owns it."""
    from pipe_nav_core.io import atomic

    real_open = os.open

    def open_then_interrupted(*args, **kwargs):
        real_open(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(atomic.os, "open", open_then_interrupted)
    with pytest.raises(KeyboardInterrupt), atomic_write(tmp_path / "out.csv"):
        pass
    assert list(tmp_path.iterdir()) == []


def test_an_interrupt_while_committing_still_commits_every_staged_file(tmp_path, monkeypatch):
    from pipe_nav_core.io import atomic

    real_replace, calls = os.replace, []

    def replace_then_interrupted(src, dst):
        real_replace(src, dst)
        calls.append(dst)
        if len(calls) == 1:
            raise KeyboardInterrupt

    targets = [tmp_path / f"{k}.csv" for k in range(3)]
    monkeypatch.setattr(atomic.os, "replace", replace_then_interrupted)
    with pytest.raises(KeyboardInterrupt), all_or_none(targets) as staged:
        for target, path in staged.items():
            path.write_text(target)
    assert sorted(tmp_path.iterdir()) == targets
    assert all(t.read_text() == str(t) for t in targets)


def test_atomic_write_replaces_and_uses_normal_permissions(tmp_path):
    p = tmp_path / "out.txt"
    with atomic_write(p) as f:
        f.write("x")
    assert p.read_text() == "x"
    umask = os.umask(0)
    os.umask(umask)
    assert (p.stat().st_mode & 0o777) == (0o666 & ~umask)
    with atomic_path(tmp_path / "y.bin") as tmp:
        tmp.write_bytes(b"abc")
    assert (tmp_path / "y.bin").read_bytes() == b"abc"


def test_gis_writer_failing_midway_keeps_old_file(tmp_path):
    traj = make_traj(n=11)
    p = tmp_path / "c.geojson"
    p.write_text("previous")
    bad = Marker("x", 1.0, 0.9, 0.1, 1.0, (float("nan"), 0.1, 0.1))  # not valid JSON
    with pytest.raises(ValueError):
        write_geojson(p, traj, [bad])
    assert p.read_text() == "previous"
    assert [x.name for x in tmp_path.iterdir()] == ["c.geojson"]


def test_ensure_not_input(tmp_path):
    a = tmp_path / "in.mcap"
    a.write_bytes(b"x")
    ensure_not_input(tmp_path / "out.mcap", [a])  # fine
    with pytest.raises(OutputIsInputError, match="refusing to overwrite"):
        ensure_not_input(a, [a])
    with pytest.raises(OutputIsInputError):
        ensure_not_input(tmp_path / "." / "in.mcap", [str(a)])
    hard = tmp_path / "hard.mcap"
    os.link(a, hard)
    with pytest.raises(OutputIsInputError):
        ensure_not_input(hard, [a])
    d = tmp_path / "bagdir"
    d.mkdir()
    with pytest.raises(OutputIsInputError, match="inside the input bag directory"):
        ensure_not_input(d / "out.mcap", [d])


def test_interpolation_is_the_whole_array_arithmetic():
    """interpolate_trajectory (compiled, sample by sample) gives what the whole-array formulas
    give: the linear columns to the bit, the slerped attitude to round-off (the compiled
    arctan2 is the C library's, numpy's its own), across the antimeridian too."""
    from pipe_nav_core.geo import attitude as att

    rng = np.random.default_rng(5)
    traj = make_traj(n=400)
    for lon0 in (0.1, math.pi - 2e-6):
        traj.lon = (lon0 + np.cumsum(np.full(400, 1e-8)) + math.pi) % (2 * math.pi) - math.pi
        traj.quat_nb = att.quat_normalize(rng.normal(size=(400, 4)))
        tq = np.sort(rng.uniform(traj.t[0] - 1.0, traj.t[-1] + 1.0, 2000))
        got = interpolate_trajectory(traj, tq)
        t = traj.t
        tc = np.clip(tq, t[0], t[-1])
        i = np.clip(np.searchsorted(t, tc, side="right") - 1, 0, len(t) - 2)
        f = np.clip((tc - t[i]) / (t[i + 1] - t[i]), 0.0, 1.0)
        for name in ("lat", "h", "distance", "vel_n", "sigma_enu"):
            a = getattr(traj, name)
            ff = f[:, None] if a.ndim > 1 else f
            assert getattr(got, name).tobytes() == (a[i] + (a[i + 1] - a[i]) * ff).tobytes(), name
        lon = np.unwrap(traj.lon)
        lon = (lon[i] + (lon[i + 1] - lon[i]) * f + math.pi) % (2 * math.pi) - math.pi
        assert got.lon.tobytes() == lon.tobytes()
        q0, q1 = traj.quat_nb[i], traj.quat_nb[i + 1]
        rv = att.rotvec_from_quat(att.quat_mul(att.quat_conj(q0), q1))
        q = att.quat_normalize(att.quat_mul(q0, att.quat_from_rotvec(rv * f[:, None])))
        assert np.abs(got.quat_nb - q).max() < 1e-15


def test_the_centreline_coordinates_made_once_serve_both_formats():
    """pipe-nav smooth makes the centreline's coordinates once, before the welds are known,
    and hands them to both writers: what they write is then those coordinates, and by
    default the ones they make themselves."""
    from pipe_nav_core.io.gis import centreline_coords, to_kml

    traj = make_traj(n=50)
    coords = centreline_coords(traj)
    assert len(coords) == 50 and coords[0] == [
        round(math.degrees(traj.lon[0]), 9), round(math.degrees(traj.lat[0]), 9),
        round(float(traj.h[0]), 4)]  # fmt: skip
    line = to_geojson(traj, coords=coords)["features"][0]["geometry"]["coordinates"]
    assert line is coords and to_geojson(traj) == to_geojson(traj, coords=coords)
    assert to_kml(traj) == to_kml(traj, coords=coords)
    other = [[1.0, 2.0, 3.0], [1.5, 2.5, 3.5]]
    assert to_geojson(traj, coords=other)["features"][0]["geometry"]["coordinates"] == other
    kml = to_kml(traj, coords=other)
    assert "1.000000000,2.000000000,3.0000 1.500000000,2.500000000,3.5000" in kml
