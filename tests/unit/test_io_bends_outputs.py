"""The bends and strain features in the outputs: /pipe_nav/bends in the smoothed bag (read back
with rosbags and the mcap reader), points in the GeoJSON / KML, the strain panel of the PNG."""

from __future__ import annotations

import json
import math
import struct
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from pipe_nav_core.app.plots import _envelope, plot_report
from pipe_nav_core.io import bag_info, write_geojson, write_kml, write_output_bag
from pipe_nav_core.io import rosmsg as R
from pipe_nav_core.io.bagwrite import message_definition
from pipe_nav_core.io.rosbag2_metadata import write_rosbag2_metadata
from pipe_nav_core.io.rosmsg import jazzy_typestore
from pipe_nav_core.io.stamps import sec_to_ns_scalar
from pipe_nav_core.products.bends import PipeBend
from pipe_nav_core.products.curvature import CurvatureProfile
from pipe_nav_core.products.integrity import IntegrityReport
from pipe_nav_core.products.strain import StrainFeature
from test_io_formats import MK
from test_io_support import DATUM, make_traj

POSE_ARRAY = "geometry_msgs/msg/PoseArray"
BENDS_TOPIC = "/pipe_nav/bends"


def _bends(traj, idx):
    """PipeBends with their apex on samples ``idx`` of traj (attitude of the sample)."""
    out = []
    for k, i in enumerate(idx):
        q = np.asarray(traj.quat_nb[i], dtype=np.float64)
        out.append(
            PipeBend(number=k + 1, start_m=float(traj.distance[i]) - 2.0,
                     apex_m=float(traj.distance[i]), end_m=float(traj.distance[i]) + 2.5,
                     lat=float(traj.lat[i]), lon=float(traj.lon[i]), alt=float(traj.h[i]),
                     angle=math.radians(3.0 + k), sigma_angle=math.radians(0.01),
                     radius=40.0 + k, sigma_radius=0.5 if k else float("nan"),
                     radius_d=100.0 + k, plane=math.radians(90.0), direction="right",
                     kind="field", apex_t=float(traj.t[i]),
                     apex_quat_nb=(float(q[0]), float(q[1]), float(q[2]), float(q[3])))
        )  # fmt: skip
    return out


def _features(bends):
    return [
        StrainFeature(number=1, threshold_pct=0.125, start_m=b.start_m, peak_m=b.apex_m,
                      end_m=b.end_m, lat=b.lat, lon=b.lon, alt=b.alt, peak_pct=0.25,
                      sigma_peak_pct=0.002, plane=b.plane, bend=b.number, construction=None)
        for b in bends[:1]
    ] + [
        StrainFeature(number=2, threshold_pct=0.2, start_m=10.0, peak_m=11.0, end_m=13.0,
                      lat=bends[-1].lat, lon=bends[-1].lon, alt=bends[-1].alt, peak_pct=0.21,
                      sigma_peak_pct=0.003, plane=0.0, bend=0, construction=False)
    ]  # fmt: skip


# ----------------------------------------------------------------------------- bag


def _read_bends(path):
    """(connection, message, log time ns) of /pipe_nav/bends via rosbags' MCAP reader."""
    from rosbags.rosbag2.storage_mcap import McapReader

    ts = jazzy_typestore()
    rd = McapReader(path)
    rd.open()
    try:
        conns = {c.topic: c for c in rd.connections}
        got = [
            (conn, ts.deserialize_cdr(raw, conn.msgtype), t)
            for conn, t, raw in rd.messages([conns[BENDS_TOPIC]])
        ]
    finally:
        rd.close()
    assert len(got) == 1
    return got[0]


def test_output_bag_has_the_bend_apexes(tmp_path):
    path = make_traj(n=401, seconds=40.0)
    bends = _bends(path, [50, 200, 333])
    out = tmp_path / "out.mcap"
    write_output_bag(out, path=path, datum=DATUM, bends=bends)
    conn, msg, log_ns = _read_bends(out)
    assert conn.msgtype == POSE_ARRAY and conn.msgcount == 1
    q = conn.ext.offered_qos_profiles[0]
    assert q.durability.name == "TRANSIENT_LOCAL" and q.reliability.name == "RELIABLE"
    assert q.depth == 1
    assert msg.header.frame_id == "map"
    # stamped like the path: its last sample, log time = header stamp
    assert R.stamp_to_ns(msg.header.stamp) == sec_to_ns_scalar(path.t[-1]) == log_ns
    assert len(msg.poses) == 3
    pos, quat = R.pose_array_from_msg(msg)
    enu = R.enu_of(DATUM, [b.lat for b in bends], [b.lon for b in bends], [b.alt for b in bends])
    np.testing.assert_allclose(pos, enu, atol=1e-9)
    # the apex lies on the path's pose at that sample
    path_enu = R.enu_of(DATUM, path.lat, path.lon, path.h)
    np.testing.assert_allclose(pos, path_enu[[50, 200, 333]], atol=1e-9)
    np.testing.assert_array_equal(quat, np.array([b.apex_quat_nb for b in bends]))


def test_bends_schema_is_the_ros2msg_definition_and_decodes_with_anyreader(tmp_path):
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    path = make_traj(n=101, seconds=10.0)
    bends = _bends(path, [10, 90])
    d = tmp_path / "run"
    d.mkdir()
    out = d / "run.mcap"
    write_output_bag(out, path=path, datum=DATUM, bends=bends)
    # the mcap library's reader: schema, encoding, type hash, CDR payload
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        ch = next(c for c in summary.channels.values() if c.topic == BENDS_TOPIC)
        schema = summary.schemas[ch.schema_id]
        assert (schema.name, schema.encoding) == (POSE_ARRAY, "ros2msg")
        assert schema.data.decode() == message_definition(POSE_ARRAY)
        assert schema.data.decode().startswith(
            "std_msgs/Header header\ngeometry_msgs/Pose[] poses\n"
        )
        assert ch.message_encoding == "cdr"
        assert ch.metadata["topic_type_hash"] == jazzy_typestore().hash_rihs01(POSE_ARRAY)
        raws = [m.data for _s, c, m in reader.iter_messages(topics=[BENDS_TOPIC])]
    assert len(raws) == 1
    msg = jazzy_typestore().deserialize_cdr(raws[0], POSE_ARRAY)
    assert len(msg.poses) == 2
    # rosbags' AnyReader of the rosbag2 directory, with the definitions stored in the bag
    write_rosbag2_metadata(out)
    with AnyReader([d], default_typestore=jazzy_typestore()) as r:
        conns = [c for c in r.connections if c.topic == BENDS_TOPIC]
        assert [(c.msgtype, c.msgcount) for c in conns] == [(POSE_ARRAY, 1)]
        msgs = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]
    assert msgs[0].header.frame_id == "map"
    pos, quat = R.pose_array_from_msg(msgs[0])
    assert np.isfinite(pos).all() and np.isfinite(quat).all()
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(
        pos, R.enu_of(DATUM, path.lat, path.lon, path.h)[[10, 90]], atol=1e-9
    )
    # and our own bag reader lists it
    info = bag_info(out)
    assert info.topics[BENDS_TOPIC].count == 1
    assert info.topics[BENDS_TOPIC].msgtype == POSE_ARRAY
    assert info.topics[BENDS_TOPIC].start == pytest.approx(path.t[-1], abs=1e-9)  # its stamp


def test_bends_topic_is_always_there_with_a_path(tmp_path):
    path = make_traj(n=51, seconds=5.0)
    out = tmp_path / "none.mcap"
    write_output_bag(out, path=path, datum=DATUM)  # no bend: an empty PoseArray
    conn, msg, _ = _read_bends(out)
    assert msg.poses == [] and msg.header.frame_id == "map"
    assert R.stamp_to_sec(msg.header.stamp) == path.t[-1]
    out2 = tmp_path / "stamped.mcap"
    write_output_bag(out2, path=path, datum=DATUM, stamp=123.5, bends=_bends(path, [7]))
    _, msg, log_ns = _read_bends(out2)
    assert R.stamp_to_sec(msg.header.stamp) == 123.5 and log_ns == sec_to_ns_scalar(123.5)
    # replay bags (no path) have no bends either
    out3 = tmp_path / "replay.mcap"
    write_output_bag(out3, path=None, datum=DATUM, odometry=path)
    assert BENDS_TOPIC not in bag_info(out3).topics


def test_smoothed_bag_reader_ignores_the_bends_topic(tmp_path):
    smoothed_bag = pytest.importorskip("pipe_nav_core.io.smoothed_bag")
    path = make_traj(n=101, seconds=10.0)
    out = tmp_path / "s.mcap"
    write_output_bag(out, path=path, datum=DATUM, bends=_bends(path, [3, 40]))
    traj, datum, _ = smoothed_bag.read_smoothed_bag(out)
    assert len(traj.t) == 101 and datum == pytest.approx(DATUM)


# ----------------------------------------------------------------------------- GIS


def test_geojson_and_kml_unchanged_without_bends(tmp_path):
    traj = make_traj(n=101, seconds=10.0)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for write, ext in ((write_geojson, "geojson"), (write_kml, "kml")):
        write(tmp_path / "a" / f"c.{ext}", traj, MK)
        write(tmp_path / "b" / f"c.{ext}", traj, MK, bends=(), strain_features=())
        a = (tmp_path / "a" / f"c.{ext}").read_bytes()
        assert a == (tmp_path / "b" / f"c.{ext}").read_bytes()
        assert b"bend" not in a and b"strain" not in a


def test_geojson_bend_and_strain_feature_points(tmp_path):
    traj = make_traj(n=101, seconds=10.0)
    bends = _bends(traj, [20, 70])
    feats = _features(bends)
    p = tmp_path / "c.geojson"
    write_geojson(p, traj, MK, bends=bends, strain_features=feats)
    doc = json.loads(p.read_text())
    kinds = [f["properties"]["kind"] for f in doc["features"]]
    assert kinds == ["centreline"] + ["marker"] * 3 + ["bend"] * 2 + ["strain_feature"] * 2
    b = [f for f in doc["features"] if f["properties"]["kind"] == "bend"]
    lon, lat, alt = b[1]["geometry"]["coordinates"]
    assert lon == pytest.approx(math.degrees(traj.lon[70]), abs=1e-9)
    assert lat == pytest.approx(math.degrees(traj.lat[70]), abs=1e-9)
    assert alt == pytest.approx(traj.h[70], abs=1e-4)
    pr = b[1]["properties"]
    assert pr["number"] == 2 and pr["class"] == "field" and pr["direction"] == "right"
    assert pr["angle_deg"] == pytest.approx(4.0) and pr["sigma_angle_deg"] == pytest.approx(0.01)
    assert pr["radius_m"] == 41.0 and pr["radius_d"] == 101.0 and pr["plane_deg"] == 90.0
    assert pr["apex_m"] == pytest.approx(traj.distance[70], abs=1e-3)
    assert b[0]["properties"]["sigma_radius_m"] is None  # NaN -> null, the file stays JSON
    s = [f["properties"] for f in doc["features"] if f["properties"]["kind"] == "strain_feature"]
    assert s[0]["bend"] == 1 and s[0]["construction"] is None and s[0]["peak_pct"] == 0.25
    assert s[0]["length_m"] == pytest.approx(4.5)
    assert s[1] == {
        "name": "strain feature 2", "kind": "strain_feature", "number": 2,
        "threshold_pct": 0.2, "peak_pct": 0.21, "sigma_peak_pct": 0.003, "plane_deg": 0.0,
        "start_m": 10.0, "peak_m": 11.0, "end_m": 13.0, "length_m": 3.0, "bend": 0,
        "construction": False,
    }  # fmt: skip


def test_an_angle_just_under_a_full_turn_is_written_in_0_to_360(tmp_path):
    """A plane of 359.97 deg (a crest curving a hair to the left) was written 360.0 in the bends
    and features CSVs and 360.00 in the strain CSV and the GeoJSON, outside the documented
    [0, 360), and an azimuth within 5e-7 deg of north 360.000000 in the centreline CSV (a pipe
    heading north crosses it often). Each writes 0 at its own rounding and keeps 359.9 /
    359.94."""
    from dataclasses import replace

    from pipe_nav_core.geo.attitude import quat_from_euler, turn_deg
    from pipe_nav_core.io.centreline import centreline_columns
    from pipe_nav_core.io.products_csv import write_bends_csv, write_strain_features_csv

    near, kept = math.radians(359.97), math.radians(359.94)
    assert float(turn_deg(near, 1)) == 0.0 and float(turn_deg(near, 2)) == 359.97
    assert float(turn_deg(math.radians(359.996), 2)) == 0.0
    assert float(turn_deg(kept, 1)) == 359.9 and float(turn_deg(-0.5 * math.pi, 1)) == 270.0
    np.testing.assert_array_equal(turn_deg(np.radians([0.0, 90.0, 359.999]), 2), [0, 90, 0])
    traj = make_traj(n=101, seconds=10.0)
    bends = [
        replace(b, plane=p, sigma_radius=0.5)
        for b, p in zip(_bends(traj, [20, 70]), (near, kept), strict=True)
    ]
    feats = [replace(f, plane=near) for f in _features(bends)]
    write_bends_csv(tmp_path / "b.csv", bends)
    write_strain_features_csv(tmp_path / "f.csv", feats)

    def planes_in(name: str) -> list[float]:  # plane_deg: column 11 of both files
        return [float(r.split(",")[11]) for r in (tmp_path / name).read_text().splitlines()[1:]]

    assert planes_in("b.csv") == [0.0, 359.9] and planes_in("f.csv") == [0.0, 0.0]
    write_geojson(tmp_path / "c.geojson", traj, MK, bends=bends, strain_features=feats)
    doc = json.loads((tmp_path / "c.geojson").read_text())
    planes = [f["properties"]["plane_deg"] for f in doc["features"] if "plane_deg" in
              f["properties"]]  # fmt: skip
    assert planes == [359.97, 359.94, 359.97, 359.97]
    north = replace(traj, quat_nb=quat_from_euler(0.0 * traj.t, 0.0 * traj.t,
                                                  0.0 * traj.t + 2.0 * math.pi - 1e-9))  # fmt: skip
    az = centreline_columns(north, DATUM)["azimuth_deg"]
    assert np.all(az == 0.0)


def test_kml_bend_and_strain_feature_placemarks(tmp_path):
    traj = make_traj(n=51, seconds=5.0)
    bends = _bends(traj, [5, 30])
    p = tmp_path / "c.kml"
    write_kml(p, traj, MK, bends=bends, strain_features=_features(bends))
    root = ET.parse(p).getroot()
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    names = [e.text for e in root.findall(".//k:Placemark/k:name", ns)]
    assert names == ["c", "launch", "agm_01", "receive", "bend 1", "bend 2",
                     "strain feature 1", "strain feature 2"]  # fmt: skip
    pms = root.findall(".//k:Placemark", ns)
    bend2 = pms[5]
    assert bend2.find("k:styleUrl", ns).text == "#bend"
    data = {d.get("name"): d.find("k:value", ns).text for d in bend2.findall(".//k:Data", ns)}
    assert data["class"] == "field" and float(data["angle_deg"]) == pytest.approx(4.0)
    assert bend2.find(".//k:altitudeMode", ns).text == "absolute"
    lon, lat, _ = (float(x) for x in bend2.find(".//k:coordinates", ns).text.split(","))
    assert lon == pytest.approx(math.degrees(traj.lon[30]), abs=1e-9)
    assert lat == pytest.approx(math.degrees(traj.lat[30]), abs=1e-9)
    sf1 = {d.get("name"): d.find("k:value", ns).text for d in pms[6].findall(".//k:Data", ns)}
    assert sf1["construction"] == "unknown" and sf1["bend"] == "1"
    assert "not construction-related" in pms[7].find("k:description", ns).text
    styles = {s.get("id") for s in root.findall(".//k:Style", ns)}
    assert styles == {"centreline", "bend", "strain_feature"}


# ----------------------------------------------------------------------------- plot


def _png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def _integrity(traj, n_rows, bends, features):
    d = np.linspace(float(traj.distance[0]), float(traj.distance[-1]), n_rows)
    kappa = 1e-4 + np.zeros(n_rows)
    for b in bends:
        kappa += (1.0 / b.radius) * np.exp(-0.5 * ((d - b.apex_m) / 1.5) ** 2)
    z = np.zeros(n_rows)
    prof = CurvatureProfile(distance=d, t=np.interp(d, traj.distance, traj.t), lat=z, lon=z,
                            alt=z, vertical=z, horizontal=kappa, total=kappa, plane=z,
                            sigma=z + 2e-5, window=1.0, pitch=z, azimuth=z)  # fmt: skip
    od = 0.3
    return IntegrityReport(prof, kappa * od * 50.0, prof.sigma * od * 50.0, list(bends),
                           list(features), od, 1.0, (0.125, 0.2))  # fmt: skip


def test_plot_report_with_the_strain_panel(tmp_path):
    traj = make_traj(n=2001, seconds=200.0)
    bends = _bends(traj, [300, 900, 1500])
    p0, p1 = tmp_path / "plain.png", tmp_path / "strain.png"
    plot_report(p0, traj, DATUM, title="t")
    plot_report(
        p1, traj, DATUM, title="t", integrity=_integrity(traj, 400, bends, _features(bends))
    )
    w0, h0 = _png_size(p0.read_bytes())
    w1, h1 = _png_size(p1.read_bytes())
    assert (w0, h0) == (1400, 1000)  # as before without integrity products
    assert w1 == w0 and h1 > h0  # a fifth, full-width panel row
    assert p1.stat().st_size > p0.stat().st_size
    # no bends, no features, an empty profile: still a figure
    empty = _integrity(traj, 0, [], [])
    plot_report(p1, traj, DATUM, integrity=empty)
    assert _png_size(p1.read_bytes()) == (w1, h1)
    # a long profile and many bends (decimated, labels thinned)
    big = make_traj(n=20001, seconds=6000.0)
    many = _bends(big, list(range(100, 20000, 150)))
    plot_report(p1, big, DATUM, integrity=_integrity(big, 120_001, many, []))
    assert _png_size(p1.read_bytes()) == (w1, h1)


def test_envelope_keeps_the_peaks():
    rng = np.random.default_rng(3)
    y = rng.normal(size=100_003)
    y[[17, 55_555, 100_002]] = [40.0, 50.0, -60.0]
    y[999] = np.nan
    idx = _envelope(y)
    assert len(idx) <= 3000 and np.all(np.diff(idx) > 0)
    assert {17, 55_555, 100_002} <= set(idx.tolist())
    np.testing.assert_array_equal(_envelope(y[:2000]), np.arange(2000))


@pytest.mark.parametrize("with_strain", [True, False])
def test_a_prepared_figure_draws_the_same_png(tmp_path, with_strain):
    """plots.prepare_figure (the plot process makes the empty figure before the data arrives)
    changes nothing in the PNG, with or without the strain panel; it is used once."""
    from pipe_nav_core.app import plots

    traj = make_traj(n=2001, seconds=200.0)
    bends = _bends(traj, [300, 900, 1500])
    integrity = _integrity(traj, 400, bends, _features(bends)) if with_strain else None
    fresh, prepared = tmp_path / "fresh.png", tmp_path / "prepared.png"
    plots._SPARE.clear()
    plot_report(fresh, traj, DATUM, title="t", integrity=integrity)
    plots.prepare_figure(with_strain)
    assert with_strain in plots._SPARE
    plot_report(prepared, traj, DATUM, title="t", integrity=integrity)
    assert not plots._SPARE
    assert prepared.read_bytes() == fresh.read_bytes()
