"""The rosbag2 metadata in the bags pipe_nav_core writes (``ros2 bag info``: ROS distro, QoS).

rosbag2's MCAP storage (ROS 2 Jazzy) keeps its bag metadata in a Metadata record named
``rosbag2`` whose key ``serialized_metadata`` holds the metadata YAML (version 9, with
``ros_distro``), and each topic's offered QoS in its Channel's ``offered_qos_profiles``; the
version decides how it reads the QoS. These tests read the records with the ``mcap`` package
(ROS-free), and on a ROS 2 machine ask rosbag2 itself (``ros2 bag info``, rosbag2_py).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from io import BytesIO
from pathlib import Path

import pytest
from mcap.reader import NonSeekingReader, make_reader
from pipe_nav_core.io import write_output_bag, write_rosbag2_metadata, write_sensor_bag
from pipe_nav_core.io.mcapwrite import McapWriter, Stream
from pipe_nav_core.io.rosbag2_metadata import (
    TOPIC_QOS,
    qos_profiles_from_text,
    yaml_text,
)
from ruamel.yaml import YAML
from test_io_support import DATUM, make_log, make_traj

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "bags" / "sample.mcap"  # written before this metadata existed (version 8 QoS)


def load_yaml(text: str):
    return YAML(typ="safe", pure=True).load(text)


def rosbag2_records(path: Path) -> tuple[list, object]:
    """(the Metadata records, the summary) of an MCAP file."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        return list(reader.iter_metadata()), reader.get_summary()


def qos_of(profile: dict) -> tuple:
    return (profile["history"], profile["depth"], profile["reliability"], profile["durability"])


def check_rosbag2_record(path: Path) -> dict:
    """The file has one ``rosbag2`` Metadata record, indexed in the summary, whose version-9
    metadata agrees with the MCAP summary and channels; returns that metadata."""
    records, summary = rosbag2_records(path)
    ours = [r for r in records if r.name == "rosbag2"]
    assert [sorted(r.metadata) for r in ours] == [["serialized_metadata"]]
    assert {r.name for r in records} <= {"rosbag2", "pipe_nav"}  # and the run's own record
    assert sorted(m.name for m in summary.metadata_indexes) == sorted(r.name for r in records)
    assert summary.statistics.metadata_count == len(records)
    meta = load_yaml(ours[0].metadata["serialized_metadata"])
    stats = summary.statistics
    assert meta["version"] == 9 and meta["ros_distro"] == "jazzy"
    assert meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == [path.name]  # the final name, not the temporary one
    assert meta["files"][0]["path"] == path.name
    assert meta["message_count"] == stats.message_count == meta["files"][0]["message_count"]
    assert meta["starting_time"]["nanoseconds_since_epoch"] == stats.message_start_time
    assert meta["duration"]["nanoseconds"] == stats.message_end_time - stats.message_start_time
    assert meta["compression_format"] == "" and meta["compression_mode"] == ""
    channels = {c.topic: c for c in summary.channels.values()}
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert set(topics) == set(channels)
    for name, t in topics.items():
        ch, tm = channels[name], t["topic_metadata"]
        assert tm["type"] == summary.schemas[ch.schema_id].name
        assert tm["serialization_format"] == "cdr"
        assert tm["type_description_hash"] == ch.metadata["topic_type_hash"]
        assert t["message_count"] == stats.channel_message_counts[ch.id]
        # the channel carries the same QoS, in the same (version 9) form
        assert load_yaml(ch.metadata["offered_qos_profiles"]) == tm["offered_qos_profiles"]
    return meta


def topic_qos(meta: dict) -> dict[str, tuple]:
    out = {}
    for t in meta["topics_with_message_count"]:
        (profile,) = t["topic_metadata"]["offered_qos_profiles"]
        out[t["topic_metadata"]["name"]] = qos_of(profile)
    return out


def test_output_bag_carries_rosbag2_metadata_and_latched_qos(tmp_path):
    out = tmp_path / "smoothed.mcap"
    write_output_bag(out, path=make_traj(n=101, seconds=10.0), datum=DATUM, odometry=make_traj())
    meta = check_rosbag2_record(out)
    assert topic_qos(meta) == {
        "/pipe_nav/path": ("keep_last", 1, "reliable", "transient_local"),
        "/pipe_nav/bends": ("keep_last", 1, "reliable", "transient_local"),
        "/pipe_nav/datum": ("keep_last", 1, "reliable", "transient_local"),
        "/pipe_nav/odometry": ("keep_last", 50, "reliable", "volatile"),
    }
    counts = {
        t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]
    }
    assert counts == {
        "/pipe_nav/path": 1,
        "/pipe_nav/bends": 1,
        "/pipe_nav/datum": 1,
        "/pipe_nav/odometry": 2001,
    }
    (profile,) = [
        t["topic_metadata"]["offered_qos_profiles"][0]
        for t in meta["topics_with_message_count"]
        if t["topic_metadata"]["name"] == "/pipe_nav/datum"
    ]
    assert profile["liveliness"] == "automatic"
    assert profile["deadline"] == {"sec": 9223372036, "nsec": 854775807}  # infinite


def test_sensor_bag_offers_reliable_data_and_latched_markers(tmp_path):
    out = tmp_path / "run.mcap"
    write_sensor_bag(out, make_log(seconds=5.0))
    meta = check_rosbag2_record(out)
    assert topic_qos(meta) == {
        "/imu/data": ("keep_last", 50, "reliable", "volatile"),
        "/odom/wheel": ("keep_last", 50, "reliable", "volatile"),
        "/imu/mag": ("keep_last", 50, "reliable", "volatile"),
        "/markers": ("keep_last", 1000, "reliable", "transient_local"),
    }
    assert meta["message_count"] == 500 + 100 + 50 + len(make_log(seconds=5.0).markers)


def test_rosbags_reads_the_qos():
    """rosbags (which reads channel QoS of versions 8 and 9) sees the same policies."""
    from rosbags.rosbag2.metadata import parse_qos

    for role, profile in TOPIC_QOS.items():
        (q,) = parse_qos(yaml_text([profile]))
        assert q.reliability.name.lower() == profile["reliability"], role
        assert q.durability.name.lower() == profile["durability"], role
        assert (q.history.name.lower(), q.depth) == ("keep_last", profile["depth"]), role


def _records(data: bytes) -> list[tuple]:
    return [
        (ch.topic, m.sequence, m.log_time, m.publish_time, m.data)
        for _, ch, m in NonSeekingReader(BytesIO(data), validate_crcs=True).iter_messages()
    ]


def test_the_metadata_record_leaves_the_messages_as_they_were():
    """The same streams written with and without the Metadata record: identical messages (and
    a reader that validates every CRC accepts both files)."""
    payloads = [bytes([k]) * (3 + k) for k in range(40)]

    def write(with_metadata: bool) -> bytes:
        f = BytesIO()
        w = McapWriter(f, chunk_size=64)
        w.add_schema(1, "std_msgs/msg/String", "ros2msg", "string data")
        w.add_channel(1, 1, "/a", "cdr", {"offered_qos_profiles": ""})
        w.add_channel(2, 1, "/b", "cdr", {"offered_qos_profiles": ""})
        w.write_streams(
            [
                Stream.variable(1, [10 * k for k in range(20)], payloads[:20]),
                Stream.variable(2, [10 * k + 5 for k in range(20)], payloads[20:]),
            ]
        )
        if with_metadata:
            w.add_metadata("rosbag2", {"serialized_metadata": "version: 9"})
        w.finish()
        return f.getvalue()

    plain, with_meta = write(False), write(True)
    assert len(_records(plain)) == 40
    assert _records(with_meta) == _records(plain)
    reader = make_reader(BytesIO(with_meta), validate_crcs=True)
    assert [(m.name, m.metadata) for m in reader.iter_metadata()] == [
        ("rosbag2", {"serialized_metadata": "version: 9"})
    ]
    assert make_reader(BytesIO(plain)).get_summary().statistics.metadata_count == 0


def test_yaml_text_round_trips():
    value = {
        "version": 9,
        "names": ["/a/b", "", "true", "a: b", "~", "#x", "café", "-1", "1.5", "null"],
        "empty": [],
        "nested": [{"k": {"x": 1, "flag": False}, "n": None}, [1, 2]],
        "s": 'with "quotes" and \\ back',
        "floats": [1.5, -0.25, 1e-06, 3e20, 0.0],
        "empty_map": {},
        "empty_in_list": [[], {}],
    }
    assert load_yaml(yaml_text(value)) == value


def test_version_8_qos_read_as_names():
    v8 = (
        "- history: 3\n  depth: 0\n  reliability: 1\n  durability: 1\n"
        "  deadline:\n    sec: 9223372036\n    nsec: 854775807\n  liveliness: 1\n"
    )
    (p,) = qos_profiles_from_text(v8)
    assert (p["history"], p["reliability"], p["durability"], p["liveliness"]) == (
        "unknown",
        "reliable",
        "transient_local",
        "automatic",
    )
    assert qos_profiles_from_text("") == [] and qos_profiles_from_text("{{not yaml") == []


def test_metadata_yaml_beside_a_bag(tmp_path):
    """write_rosbag2_metadata: version 9 metadata.yaml with QoS names, also for a bag written
    before this change (version 8 enum numbers in its channels), which rosbags opens."""
    from rosbags.highlevel import AnyReader

    old = tmp_path / "old"
    old.mkdir()
    shutil.copy(SAMPLE, old / SAMPLE.name)
    new = tmp_path / "new"
    new.mkdir()
    write_output_bag(new / "out.mcap", path=make_traj(n=11), datum=DATUM, odometry=make_traj(n=21))
    for d, bag in ((old, old / SAMPLE.name), (new, new / "out.mcap")):
        info = load_yaml(Path(write_rosbag2_metadata(bag)).read_text())[
            "rosbag2_bagfile_information"
        ]
        assert info["version"] == 9 and info["ros_distro"] == "jazzy"
        assert info["relative_file_paths"] == [bag.name]
        qos = topic_qos(info)
        assert all(q[2] == "reliable" for q in qos.values()), qos
        with AnyReader([d]) as reader:
            seen = {c.topic: c for c in reader.connections}
            assert {t: c.msgcount for t, c in seen.items()} == {
                t["topic_metadata"]["name"]: t["message_count"]
                for t in info["topics_with_message_count"]
            }
    new_qos = topic_qos(
        load_yaml((new / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    )
    assert new_qos["/pipe_nav/datum"][3] == "transient_local"
    assert new_qos["/pipe_nav/odometry"][3] == "volatile"


# ------------------------------------------------------------------------- with ROS 2 Jazzy


def test_ros2_bag_info_shows_the_distro_and_rosbag2_reads_the_qos(tmp_path):
    """``ros2 bag info`` on what ``pipe-nav smooth --out`` wrote: ROS distro jazzy, the topics
    with their counts; rosbag2 itself (rosbag2_py) reads the latched QoS of path and datum."""
    pytest.importorskip("rclpy", reason="rclpy (ROS 2 Jazzy) is not installed here")
    rosbag2_py = pytest.importorskip("rosbag2_py", reason="rosbag2_py is not installed here")
    ros2 = shutil.which("ros2")
    if ros2 is None:
        pytest.skip("the ros2 command is not on PATH (source .ci/ros-env)")
    from pipe_nav_core.app.cli import main

    out = tmp_path / "smoothed.mcap"
    assert main(["smooth", str(SAMPLE), "--out", str(out), "--quiet"]) == 0
    info = subprocess.run(
        [ros2, "bag", "info", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
        env=dict(os.environ, ROS_DOMAIN_ID=str(60 + os.getpid() % 60)),
    )
    assert info.returncode == 0, info.stdout + info.stderr
    assert re.search(r"^ROS Distro:\s+jazzy$", info.stdout, re.M), info.stdout
    listed = dict(re.findall(r"Topic: (\S+) \| Type: \S+ \| Count: (\d+)", info.stdout))
    meta = check_rosbag2_record(out)
    assert listed == {
        t["topic_metadata"]["name"]: str(t["message_count"])
        for t in meta["topics_with_message_count"]
    }
    assert listed["/pipe_nav/path"] == "1" and int(listed["/pipe_nav/odometry"]) > 1000

    # rosbag2's own reading of the file, written back out by rosbag2 as metadata.yaml
    bag_meta = rosbag2_py.Info().read_metadata(str(out), "mcap")
    assert bag_meta.ros_distro == "jazzy" and bag_meta.version == 9
    rosbag2_py.MetadataIo().write_metadata(str(tmp_path), bag_meta)
    seen = topic_qos(
        load_yaml((tmp_path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    )
    assert seen["/pipe_nav/path"] == ("keep_last", 1, "reliable", "transient_local")
    assert seen["/pipe_nav/datum"] == ("keep_last", 1, "reliable", "transient_local")
    assert seen["/pipe_nav/bends"] == ("keep_last", 1, "reliable", "transient_local")
    assert seen["/pipe_nav/odometry"] == ("keep_last", 50, "reliable", "volatile")
