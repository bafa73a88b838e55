"""Bag reading and writing: round trips, rosbags/mcap compatibility, robustness, streaming."""

from __future__ import annotations

import hashlib
import math
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.geo.attitude import dcm_from_quat
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.io import (
    BagError,
    BagReport,
    OutputIsInputError,
    TopicNames,
    bag_info,
    bag_time_range,
    concat_logs,
    iter_bag,
    read_bag,
    write_output_bag,
    write_sensor_bag,
)
from pipe_nav_core.io import rosmsg as R
from pipe_nav_core.io.rosmsg import jazzy_typestore
from pipe_nav_core.io.stamps import sec_to_ns, sec_to_ns_scalar
from pipe_nav_core.types import SensorLog
from test_io_support import (
    DATUM,
    assert_logs_equal,
    log_messages,
    make_log,
    make_traj,
    write_rosbags_dir,
)

SMALL_CHUNK = 16 * 1024  # many MCAP chunks even for small test logs


@pytest.fixture(scope="module")
def log() -> SensorLog:
    return make_log(seconds=20.0)


@pytest.fixture(scope="module")
def bag(tmp_path_factory, log) -> Path:
    p = tmp_path_factory.mktemp("bag") / "run.mcap"
    write_sensor_bag(p, log, chunk_size=SMALL_CHUNK)
    return p


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


# ----------------------------------------------------------------------------- round trip


def test_write_read_round_trip_exact(bag, log):
    got, rep = read_bag(bag)
    assert_logs_equal(got, log)
    # stamps to the nanosecond
    np.testing.assert_array_equal(sec_to_ns(got.imu.t), sec_to_ns(log.imu.t))
    assert rep.counts == {"/imu/data": 2000, "/odom/wheel": 400, "/imu/mag": 200, "/markers": 3}
    assert rep.skipped == {} and not rep.truncated and rep.warnings == []


def test_written_bag_opens_with_rosbags(bag, log):
    from rosbags.rosbag2.storage_mcap import McapReader

    ts = jazzy_typestore()
    rd = McapReader(bag)
    rd.open()
    try:
        conns = {c.topic: c for c in rd.connections}
        assert {t: c.msgtype for t, c in conns.items()} == {
            "/imu/data": "sensor_msgs/msg/Imu",
            "/odom/wheel": "nav_msgs/msg/Odometry",
            "/imu/mag": "sensor_msgs/msg/MagneticField",
            "/markers": "sensor_msgs/msg/NavSatFix",
        }
        assert {t: c.msgcount for t, c in conns.items()} == {
            "/imu/data": 2000,
            "/odom/wheel": 400,
            "/imu/mag": 200,
            "/markers": 3,
        }
        seen: dict[str, int] = {}
        last = -1
        for conn, stamp, raw in rd.messages(rd.connections):
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            assert stamp >= last  # log time order
            last = stamp
            assert stamp == R.stamp_to_ns(msg.header.stamp)  # log_time = header stamp
            k = seen.get(conn.topic, 0)
            seen[conn.topic] = k + 1
            if conn.topic == "/imu/data":
                assert msg.header.frame_id == "imu_link"
                assert msg.orientation_covariance[0] == -1.0
                assert msg.angular_velocity.y == log.imu.gyro[k, 1]
                assert msg.linear_acceleration.z == log.imu.accel[k, 2]
            elif conn.topic == "/odom/wheel":
                assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "base_link")
                assert msg.pose.pose.position.x == log.odometer.distance[k]
                assert msg.twist.twist.linear.x == log.odometer.speed[k]
                assert msg.pose.pose.position.y == 0.0 and msg.twist.twist.angular.z == 0.0
            elif conn.topic == "/imu/mag":
                assert msg.header.frame_id == "imu_link"
                assert msg.magnetic_field.x == log.mag.field[k, 0]
            else:
                mk = log.markers[k]
                assert msg.header.frame_id == mk.name
                assert msg.latitude == pytest.approx(math.degrees(mk.lat), abs=1e-12)
                assert msg.position_covariance_type == 2
                assert msg.position_covariance[4] == pytest.approx(mk.sigma_enu[1] ** 2)
        assert seen == {"/imu/data": 2000, "/odom/wheel": 400, "/imu/mag": 200, "/markers": 3}
    finally:
        rd.close()


def test_written_bag_is_valid_ros2_mcap(bag):
    from mcap.reader import NonSeekingReader, make_reader
    from rosbags.rosbag2.metadata import parse_qos

    with open(bag, "rb") as f:
        r = make_reader(f, validate_crcs=True)
        assert r.get_header().profile == "ros2"
        s = r.get_summary()
        assert s.statistics.message_count == 2603
        for sch in s.schemas.values():
            assert sch.encoding == "ros2msg"
            text = sch.data.decode()
            assert "\nstd_msgs/Header header\n" in "\n" + text.split("=" * 80)[0]
            assert "=" * 80 + "\nMSG: builtin_interfaces/Time\n" in text
        for ch in s.channels.values():
            assert ch.message_encoding == "cdr"
            qos = parse_qos(ch.metadata["offered_qos_profiles"])
            assert len(qos) == 1 and qos[0].reliability.name == "RELIABLE"
            assert ch.metadata["topic_type_hash"].startswith("RIHS01_")
        n = sum(1 for _ in r.iter_messages(log_time_order=True))
        assert n == 2603
        f.seek(0)
        # the linear reader checks the data section and every chunk's CRC
        assert sum(1 for _ in NonSeekingReader(f, validate_crcs=True).iter_messages()) == 2603


def test_rosbag2_directory_reads_like_single_file(tmp_path, log):
    d = write_rosbags_dir(tmp_path / "rb2", log_messages(log))
    assert (d / "metadata.yaml").is_file()
    got, rep = read_bag(d)
    assert_logs_equal(got, log)
    assert not rep.truncated


def test_split_directory_in_metadata_order_and_without_metadata(tmp_path, log):
    half = 1010.0
    first = SensorLog(
        imu=log.imu.slice(log.imu.t < half),
        odometer=log.odometer.slice(log.odometer.t < half),
        mag=log.mag.slice(log.mag.t < half),
        markers=[m for m in log.markers if m.t < half],
    )
    second = SensorLog(
        imu=log.imu.slice(log.imu.t >= half),
        odometer=log.odometer.slice(log.odometer.t >= half),
        mag=log.mag.slice(log.mag.t >= half),
        markers=[m for m in log.markers if m.t >= half],
    )
    d = tmp_path / "split"
    d.mkdir()
    # names sort the wrong way round: metadata.yaml order must win
    write_sensor_bag(d / "b_0.mcap", first, chunk_size=SMALL_CHUNK)
    write_sensor_bag(d / "a_1.mcap", second, chunk_size=SMALL_CHUNK)
    (d / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 8\n  storage_identifier: mcap\n"
        "  relative_file_paths:\n  - b_0.mcap\n  - a_1.mcap\n"
    )
    got, _ = read_bag(d)
    assert_logs_equal(got, log)
    # without metadata.yaml the files are taken in name order
    d2 = tmp_path / "nometa"
    d2.mkdir()
    shutil.copy(d / "b_0.mcap", d2 / "x_0.mcap")
    shutil.copy(d / "a_1.mcap", d2 / "x_1.mcap")
    got2, _ = read_bag(d2)
    assert_logs_equal(got2, log)


# ----------------------------------------------------------------------------- robustness


def test_truncated_file_gives_prefix_and_flag(tmp_path, bag, log):
    data = bag.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.55)])
    before = _sha(cut)
    got, rep = read_bag(cut)
    assert rep.truncated
    assert any("truncated" in w for w in rep.warnings)
    n = len(got.imu)
    assert 0 < n < len(log.imu)
    # exactly a prefix of the original data (nothing invented, nothing reordered)
    np.testing.assert_array_equal(got.imu.t, log.imu.t[:n])
    np.testing.assert_array_equal(got.imu.gyro, log.imu.gyro[:n])
    np.testing.assert_array_equal(got.odometer.t, log.odometer.t[: len(got.odometer)])
    assert _sha(cut) == before  # input untouched


def test_cut_inside_a_chunk_recovers_part_of_it(tmp_path, log):
    p = tmp_path / "one_chunk.mcap"
    write_sensor_bag(p, log, chunk_size=1 << 30)  # a single chunk
    data = p.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    got, rep = read_bag(cut)
    assert rep.truncated
    assert 0 < len(got.imu) < len(log.imu)
    np.testing.assert_array_equal(got.imu.accel, log.imu.accel[: len(got.imu)])


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"", "empty file"),
        (b"this is not a bag at all, just text" * 10, "not an MCAP file \\(bad magic\\)"),
        (b"\x89MCAP0\r\n\x01\x05", "before any message"),
    ],
)
def test_unreadable_files_raise_one_line_bag_error(tmp_path, content, match):
    p = tmp_path / "x.mcap"
    p.write_bytes(content)
    with pytest.raises(BagError, match=match) as ei:
        read_bag(p)
    msg = str(ei.value)
    assert "\n" not in msg and msg.startswith(str(p))


def test_missing_path_raises(tmp_path):
    with pytest.raises(BagError, match="no such file"):
        read_bag(tmp_path / "nope.mcap")


def test_corrupt_chunk_is_skipped_and_counted(tmp_path, bag, log):
    from pipe_nav_core.io.mcapread import read_summary

    s = read_summary(bag)
    ci = s.chunk_indexes[len(s.chunk_indexes) // 2]
    data = bytearray(bag.read_bytes())
    mid = ci.chunk_start_offset + ci.chunk_length // 2
    data[mid : mid + 64] = bytes(64)  # wipe part of the compressed data
    p = tmp_path / "corrupt.mcap"
    p.write_bytes(bytes(data))
    got, rep = read_bag(p)
    assert rep.truncated
    assert rep.skipped.get("corrupt_chunk", 0) > 0
    lost = sum(rep.skipped_by_topic[t].get("corrupt_chunk", 0) for t in rep.skipped_by_topic)
    total_in = len(log.imu) + len(log.odometer) + len(log.mag) + len(log.markers)
    total_out = len(got.imu) + len(got.odometer) + len(got.mag) + len(got.markers)
    assert total_out + lost == total_in
    assert np.all(np.diff(got.imu.t) > 0)


def test_nan_samples_dropped_and_counted(tmp_path, log):
    bad = make_log(seconds=5.0)
    bad.imu.gyro[[3, 10, 11]] = np.nan
    bad.imu.accel[20, 2] = np.inf
    bad.odometer.distance[7] = np.nan
    bad.mag.field[0, 0] = -np.inf
    p = tmp_path / "nan.mcap"
    write_sensor_bag(p, bad)
    got, rep = read_bag(p)
    assert len(got.imu) == len(bad.imu) - 4
    assert np.isfinite(got.imu.gyro).all() and np.isfinite(got.imu.accel).all()
    assert rep.skipped_by_topic["/imu/data"] == {"nan": 4}
    assert rep.skipped_by_topic["/odom/wheel"] == {"nan": 1}
    assert rep.skipped_by_topic["/imu/mag"] == {"nan": 1}
    assert rep.skipped["nan"] == 6
    assert not np.isin(bad.imu.t[[3, 10, 11, 20]], got.imu.t).any()


def _stamped_imu_bag(tmp_path: Path, stamps: list[float], name: str = "ooo") -> Path:
    """IMU messages recorded (log time, file order) one per 10 ms, with the given stamps."""
    types = R.rosbags_types()
    msgs = [
        (
            "/imu/data",
            "sensor_msgs/msg/Imu",
            sec_to_ns_scalar(100.0 + 0.01 * i),
            R.imu_to_msg(types, s, [float(i), 0.0, 0.0], [0.0, 0.0, 9.8]),
        )
        for i, s in enumerate(stamps)
    ]
    return write_rosbags_dir(tmp_path / name, msgs)


def test_out_of_order_sorted_backwards_and_duplicates_dropped(tmp_path):
    stamps = [100.0 + 0.01 * i for i in range(300)]
    stamps[10], stamps[11] = stamps[11], stamps[10]  # 10 ms disorder: repaired
    stamps[50], stamps[53] = stamps[53], stamps[50]  # 30 ms disorder: repaired
    stamps[100] = stamps[100] - 2.0  # 2 s backwards: dropped
    stamps[150] = stamps[149]  # duplicate: dropped
    stamps[200] = stamps[200] + 500.0  # isolated jump ahead (clock glitch): dropped
    got, rep = read_bag(_stamped_imu_bag(tmp_path, stamps))
    assert np.all(np.diff(got.imu.t) > 0)
    assert len(got.imu) == 297
    assert rep.skipped_by_topic["/imu/data"] == {
        "non_monotonic": 1,
        "duplicate": 1,
        "time_jump": 1,
    }
    # the gyro x holds the recording index: the swapped samples come back in stamp order
    idx = got.imu.gyro[:, 0].astype(int).tolist()
    assert idx[10:12] == [11, 10]
    assert 100 not in idx and 150 not in idx and 200 not in idx
    assert idx.index(53) < idx.index(51) < idx.index(50)


def test_a_message_written_late_is_sorted_into_place(tmp_path):
    """A message the recorder wrote 1.3 s after its neighbours, its log time as late as its
    stamp (rosbag2's message compression under load does so): kept and sorted into place,
    where a stamp that far back with its log time on time (a clock stepping back) is
    dropped."""
    types = R.rosbags_types()

    def bag(name: str, late_log: bool) -> Path:
        order = [i for i in range(300) if i != 100]
        order.insert(230, 100)  # message 100 written after message 229
        msgs = []
        for pos, i in enumerate(order):
            stamp = 100.0 + 0.01 * i
            logged = stamp if late_log else 100.0 + 0.01 * pos  # as late, or on time
            msg = R.imu_to_msg(types, stamp, [float(i), 0.0, 0.0], [0.0, 0.0, 9.8])
            msgs.append(("/imu/data", "sensor_msgs/msg/Imu", sec_to_ns_scalar(logged), msg))
        return write_rosbags_dir(tmp_path / name, msgs)

    got, rep = read_bag(bag("late", late_log=True))
    assert got.imu.gyro[:, 0].astype(int).tolist() == list(range(300)) and rep.skipped == {}
    stepped, rep = read_bag(bag("stepped", late_log=False))
    assert len(stepped.imu) == 299 and rep.skipped_by_topic["/imu/data"] == {"non_monotonic": 1}


def test_a_topic_stamped_seconds_behind_the_others_is_read_whole(tmp_path):
    """An IMU whose driver stamps its samples 12 s behind the host's clock, recorded as it
    arrives (its log times 12 s after its stamps): read in time chunks (what pipe-nav smooth
    does, the first pass beside the reading) as whole as at once; the chunks wait for the
    slowest topic (bagread.STALL_S). Before, 0.5-1 % of its samples were dropped as late."""
    log = make_log(seconds=400.0)
    lag = sec_to_ns_scalar(12.0)
    msgs = [(topic, kind, ns + (lag if topic == "/imu/data" else 0), m)
            for topic, kind, ns, m in log_messages(log)]  # fmt: skip
    bag = write_rosbags_dir(tmp_path / "lagging", sorted(msgs, key=lambda m: m[2]))
    pieces: list[SensorLog] = []
    chunked, rep = read_bag(bag, pieces=lambda piece, _r: pieces.append(piece))
    whole, rep_whole = read_bag(bag)
    assert len(pieces) > 3 and rep.skipped == {} == rep_whole.skipped
    assert_logs_equal(chunked, whole)
    assert len(whole.imu) == len(log.imu)


def test_genuine_time_gap_is_kept(tmp_path):
    stamps = [100.0 + 0.01 * i for i in range(100)] + [300.0 + 0.01 * i for i in range(100)]
    got, rep = read_bag(_stamped_imu_bag(tmp_path, stamps, "gap"))
    assert len(got.imu) == 200 and rep.skipped == {}


def test_wrong_type_on_topic_and_missing_topics(tmp_path):
    types = R.rosbags_types()
    msgs = []
    for i in range(50):
        t = 10.0 + 0.01 * i
        ns = sec_to_ns_scalar(t)
        msgs.append(
            ("/imu/data", "sensor_msgs/msg/Imu", ns, R.imu_to_msg(types, t, [1, 2, 3], [0, 0, 9.8]))
        )
        # an Imu where the magnetometer should be
        msgs.append(
            ("/imu/mag", "sensor_msgs/msg/Imu", ns, R.imu_to_msg(types, t, [0, 0, 0], [0, 0, 0]))
        )
    got, rep = read_bag(write_rosbags_dir(tmp_path / "wrong", msgs))
    assert len(got.imu) == 50
    assert len(got.mag) == 0 and got.mag.field.shape == (0, 3)
    assert len(got.odometer) == 0 and got.markers == []
    assert rep.skipped_by_topic["/imu/mag"] == {"unknown_type": 50}
    assert rep.types["/imu/mag"] == "sensor_msgs/msg/Imu"
    text = " | ".join(rep.warnings)
    assert "/imu/mag: carries sensor_msgs/msg/Imu, expected sensor_msgs/msg/MagneticField" in text
    assert "/odom/wheel: no messages" in text and "/markers: no messages" in text


def test_custom_topic_names(tmp_path, log):
    p = tmp_path / "renamed.mcap"
    names = TopicNames(imu="/pig/imu", odometer="/pig/odo", mag="/pig/mag", markers="/agm")
    write_sensor_bag(p, log, topics=names)
    got, rep = read_bag(p, names)
    assert_logs_equal(got, log)
    empty, rep2 = read_bag(p)  # default names: nothing there
    assert len(empty.imu) == 0 and any("/imu/data: no messages" in w for w in rep2.warnings)


# ----------------------------------------------------------------------------- streaming


def test_iter_bag_chunks_concatenate_to_read_bag(bag, log):
    rep = BagReport()
    chunks = list(iter_bag(bag, chunk_seconds=3.0, report=rep))
    full, _ = read_bag(bag)
    assert len(chunks) >= 6
    assert_logs_equal(concat_logs(chunks), full)
    assert rep.counts == {"/imu/data": 2000, "/odom/wheel": 400, "/imu/mag": 200, "/markers": 3}
    for c in chunks:
        ts = np.concatenate([c.imu.t, c.odometer.t, c.mag.t, [m.t for m in c.markers]])
        k = math.floor(ts.min() / 3.0)
        assert ts.max() < (k + 1) * 3.0  # one time chunk, markers included
    # the generator's return value is the report as well
    gen = iter_bag(bag, chunk_seconds=3.0)
    with pytest.raises(StopIteration) as stop:
        while True:
            next(gen)
    assert stop.value.value.counts["/imu/data"] == 2000


def test_iter_bag_with_disorder_matches_read_bag(tmp_path):
    rng = np.random.default_rng(3)
    stamps = (100.0 + 0.01 * np.arange(2000) + rng.uniform(-0.2, 0.2, 2000)).tolist()
    p = _stamped_imu_bag(tmp_path, stamps, "jitter")
    full, rep_full = read_bag(p)
    rep = BagReport()
    parts = list(iter_bag(p, chunk_seconds=1.0, report=rep))
    assert len(parts) > 10
    assert_logs_equal(concat_logs(parts), full)
    assert np.all(np.diff(concat_logs(parts).imu.t) > 0)
    assert rep.skipped == rep_full.skipped


def test_iter_bag_raises_bag_error_eagerly(tmp_path):
    p = tmp_path / "g.mcap"
    p.write_bytes(b"garbage" * 10)
    with pytest.raises(BagError):
        iter_bag(p)


# ----------------------------------------------------------------------------- info


def test_bag_info_and_time_range(bag, log):
    info = bag_info(bag)
    assert info.indexed and not info.truncated
    assert info.message_count == 2603
    imu = info.topics["/imu/data"]
    assert (imu.msgtype, imu.count) == ("sensor_msgs/msg/Imu", 2000)
    assert imu.start == log.imu.t[0] and imu.end == log.imu.t[-1]
    assert info.topics["/markers"].start == log.markers[0].t
    assert bag_time_range(bag) == (log.imu.t[0], log.imu.t[-1])
    assert bag_time_range(bag, ["/markers"]) == (log.markers[0].t, log.markers[-1].t)
    # without a summary the same facts come from a scan
    data = bag.read_bytes()
    from pipe_nav_core.io.mcapread import read_summary

    cut = bag.parent / "nosummary.mcap"
    cut.write_bytes(data[: read_summary(bag).chunk_indexes[-1].chunk_start_offset + 10])
    info2 = bag_info(cut)
    assert not info2.indexed and info2.truncated
    assert 0 < info2.topics["/imu/data"].count < 2000


# ----------------------------------------------------------------------------- output bag


def test_write_output_bag_contents(tmp_path):
    from rosbags.rosbag2.metadata import parse_qos
    from rosbags.rosbag2.storage_mcap import McapReader

    path = make_traj(n=401, seconds=40.0)
    odo = make_traj(n=801, seconds=40.0)
    out = tmp_path / "out.mcap"
    write_output_bag(out, path=path, datum=DATUM, odometry=odo)
    ts = jazzy_typestore()
    rd = McapReader(out)
    rd.open()
    try:
        conns = {c.topic: c for c in rd.connections}
        assert conns["/pipe_nav/path"].msgtype == "nav_msgs/msg/Path"
        assert conns["/pipe_nav/datum"].msgtype == "sensor_msgs/msg/NavSatFix"
        assert conns["/pipe_nav/odometry"].msgcount == 801
        for topic in ("/pipe_nav/path", "/pipe_nav/datum"):
            q = conns[topic].ext.offered_qos_profiles
            assert q[0].durability.name == "TRANSIENT_LOCAL"
        assert parse_qos  # imported for the side effect check above
        odoms = []
        for conn, _, raw in rd.messages(rd.connections):
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == "/pipe_nav/path":
                assert msg.header.frame_id == "map" and len(msg.poses) == 401
                enu = geodetic_to_enu(path.lat, path.lon, path.h, DATUM.lat, DATUM.lon, DATUM.alt)
                p7 = msg.poses[7]
                assert p7.header.frame_id == "map"
                assert R.stamp_to_ns(p7.header.stamp) == sec_to_ns_scalar(path.t[7])
                assert p7.pose.position.x == pytest.approx(enu[7, 0], abs=1e-9)
                assert p7.pose.position.z == pytest.approx(enu[7, 2], abs=1e-9)
                assert p7.pose.orientation.w == path.quat_nb[7, 3]
                assert R.stamp_to_sec(msg.header.stamp) == path.t[-1]
            elif conn.topic == "/pipe_nav/datum":
                assert msg.header.frame_id == "map"
                assert msg.latitude == pytest.approx(math.degrees(DATUM.lat), abs=1e-12)
                assert msg.altitude == DATUM.alt
            else:
                odoms.append(msg)
        k = 300
        m = odoms[k]
        assert (m.header.frame_id, m.child_frame_id) == ("map", "base_link")
        v_b = dcm_from_quat(odo.quat_nb[k]).T @ odo.vel_n[k]
        np.testing.assert_allclose(
            [m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z],
            v_b,
            atol=1e-12,
        )
        cov = np.asarray(m.pose.covariance).reshape(6, 6)
        np.testing.assert_allclose(np.diag(cov)[:3], odo.sigma_enu[k] ** 2, rtol=1e-12)
        assert cov[0, 1] == 0.0
    finally:
        rd.close()


def test_output_bag_refuses_to_overwrite_input(tmp_path, bag):
    before = _sha(bag)
    with pytest.raises(OutputIsInputError):
        write_output_bag(bag, path=make_traj(n=11), datum=DATUM, inputs=[bag])
    link = tmp_path / "link.mcap"
    link.symlink_to(bag)
    with pytest.raises(OutputIsInputError):
        write_output_bag(link, path=make_traj(n=11), datum=DATUM, inputs=[bag])
    assert _sha(bag) == before


def test_reading_never_modifies_input(bag):
    before = _sha(bag)
    mtime = bag.stat().st_mtime_ns
    read_bag(bag)
    list(iter_bag(bag, chunk_seconds=5.0))
    bag_info(bag)
    assert _sha(bag) == before and bag.stat().st_mtime_ns == mtime


def test_write_rejects_negative_stamps(tmp_path):
    lg = make_log(seconds=1.0, t0=-5.0, n_markers=0)
    with pytest.raises(ValueError, match="stamps"):
        write_sensor_bag(tmp_path / "neg.mcap", lg)
    assert not (tmp_path / "neg.mcap").exists()
    assert list(tmp_path.iterdir()) == []  # no temporary file left behind


def test_unsorted_log_is_written_sorted(tmp_path, log):
    order = np.random.default_rng(1).permutation(len(log.imu))
    shuffled = SensorLog(
        imu=log.imu.slice(order),
        odometer=log.odometer,
        mag=log.mag,
        markers=list(reversed(log.markers)),
    )
    p = tmp_path / "s.mcap"
    write_sensor_bag(p, shuffled)
    got, _ = read_bag(p)
    assert_logs_equal(got, log)


def test_message_record_layout_is_what_mcap_expects(bag):
    # First record after the magic is the Header with profile "ros2".
    data = bag.read_bytes()
    assert data[:8] == b"\x89MCAP0\r\n" and data[-8:] == b"\x89MCAP0\r\n"
    op, length = struct.unpack_from("<BQ", data, 8)
    assert op == 1
    (plen,) = struct.unpack_from("<I", data, 17)
    assert data[21 : 21 + plen] == b"ros2"


@pytest.mark.parametrize(
    ("compression", "chunking"), [("LZ4", True), ("NONE", True), ("ZSTD", False)]
)
def test_bags_from_the_mcap_library_writer(tmp_path, log, compression, chunking):
    """Files written by another MCAP writer (lz4, uncompressed, unchunked) read the same."""
    from mcap.writer import CompressionType, Writer
    from pipe_nav_core.io.bagwrite import message_definition

    ts = jazzy_typestore()
    p = tmp_path / "other.mcap"
    with open(p, "wb") as f:
        w = Writer(
            f,
            chunk_size=8192,
            compression=getattr(CompressionType, compression),
            use_chunking=chunking,
        )
        w.start(profile="ros2", library="test")
        chans = {}
        for topic, typename, ns, msg in log_messages(log):
            if topic not in chans:
                sid = w.register_schema(typename, "ros2msg", message_definition(typename).encode())
                chans[topic] = w.register_channel(topic, "cdr", sid)
            w.add_message(chans[topic], ns, bytes(ts.serialize_cdr(msg, typename)), ns)
        w.finish()
    got, rep = read_bag(p)
    assert_logs_equal(got, log)
    assert not rep.truncated
    parts = list(iter_bag(p, chunk_seconds=4.0))
    assert_logs_equal(concat_logs(parts), log)


def test_big_endian_and_broken_payloads(tmp_path):
    """Big-endian CDR goes through the generic decoder; undecodable payloads are counted."""
    ts = jazzy_typestore()
    types = R.rosbags_types()
    msgs = []
    for i in range(40):
        t = 5.0 + 0.01 * i
        m = R.imu_to_msg(types, t, [float(i), 0.5, -0.5], [0.0, 0.0, 9.8])
        if i % 4 == 1:
            raw = bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu", little_endian=False))
        elif i in (10, 22):
            raw = bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu"))[:30]  # cut short
        else:
            raw = bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu"))
        msgs.append(("/imu/data", "sensor_msgs/msg/Imu", sec_to_ns_scalar(t), raw))
    got, rep = read_bag(write_rosbags_dir(tmp_path / "be", msgs))
    assert rep.skipped_by_topic["/imu/data"] == {"bad_cdr": 2}
    assert got.imu.gyro[:, 0].tolist() == [float(i) for i in range(40) if i not in (10, 22)]
    np.testing.assert_array_equal(got.imu.gyro[:, 1], 0.5)
    assert np.all(np.diff(got.imu.t) > 0)


def test_metadata_yaml_path_is_the_bag(tmp_path, log):
    d = write_rosbags_dir(tmp_path / "rb", log_messages(log))
    got, _ = read_bag(d / "metadata.yaml")
    assert_logs_equal(got, log)


def test_glitch_on_the_first_stamp_does_not_block_the_topic(tmp_path):
    stamps = [100.0 + 0.01 * i for i in range(50)]
    stamps[0] += 1000.0
    got, rep = read_bag(_stamped_imu_bag(tmp_path, stamps, "first"))
    assert len(got.imu) == 49
    assert rep.skipped_by_topic["/imu/data"] == {"time_jump": 1}


def test_anyreader_opens_written_bag_via_its_directory(tmp_path, log):
    from pipe_nav_core.io.rosbag2_metadata import write_rosbag2_metadata
    from rosbags.highlevel import AnyReader

    d = tmp_path / "as_dir"
    d.mkdir()
    write_sensor_bag(d / "as_dir.mcap", log, chunk_size=SMALL_CHUNK)
    write_rosbag2_metadata(d / "as_dir.mcap")
    with AnyReader([d], default_typestore=jazzy_typestore()) as r:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in r.connections}
        assert topics["/imu/data"] == ("sensor_msgs/msg/Imu", 2000)
        assert topics["/markers"] == ("sensor_msgs/msg/NavSatFix", 3)
        frames = set()
        n = 0
        for conn, _, raw in r.messages():
            msg = r.deserialize(raw, conn.msgtype)  # uses the definitions stored in the bag
            frames.add((conn.topic, msg.header.frame_id))
            n += 1
        assert n == 2603
        assert ("/imu/data", "imu_link") in frames and ("/odom/wheel", "odom") in frames
        assert ("/markers", "agm_01") in frames
    got, _ = read_bag(d)  # and our reader takes the directory as well
    assert_logs_equal(got, log)


def test_output_bag_without_path_for_replay(tmp_path):
    from rosbags.rosbag2.storage_mcap import McapReader

    odo = make_traj(n=101, seconds=10.0)
    out = tmp_path / "replay.mcap"
    write_output_bag(out, path=None, datum=DATUM, odometry=odo)
    rd = McapReader(out)
    rd.open()
    try:
        assert {c.topic: c.msgcount for c in rd.connections} == {
            "/pipe_nav/datum": 1,
            "/pipe_nav/odometry": 101,
        }
    finally:
        rd.close()


@pytest.mark.parametrize("spill", [30_000, 0, 10**9])
def test_a_large_imu_is_gathered_in_files_as_it_is_read(bag, monkeypatch, spill):
    """read_bag(spill_imu_bytes=N): once more than N bytes of IMU samples are read, they go to
    files as the chunks come (those read before too) and the log's IMU is mapped from them,
    read-only: the same log, bit for bit, as read whole; under N, in memory as before."""
    from pipe_nav_core.io import bagread

    from pipe_nav_core import memory

    monkeypatch.setattr(bagread, "PIECE_S", 2.0)  # several chunks: some before the spill
    told: list[SensorLog] = []
    got, rep = read_bag(bag, pieces=lambda piece, _r: told.append(piece), spill_imu_bytes=spill)
    whole, rep_whole = read_bag(bag)
    assert len(told) >= 5 and rep.counts == rep_whole.counts
    assert_logs_equal(got, whole)
    for a, b in zip((got.imu.t, got.imu.gyro, got.imu.accel), (whole.imu.t, whole.imu.gyro,
                                                             whole.imu.accel)):  # fmt: skip
        assert a.tobytes() == b.tobytes()
        assert (memory.mapping(a) is not None) == (spill < 10**9)
        assert a.flags.writeable == (spill >= 10**9)
    # the chunks handed out keep their own samples (the first pass beside the reading feeds
    # on them): none is emptied by the spill
    assert sum(len(p.imu) for p in told) == len(whole.imu)
    alone, _ = read_bag(bag, spill_imu_bytes=spill)  # without pieces: the same
    assert_logs_equal(alone, whole)
