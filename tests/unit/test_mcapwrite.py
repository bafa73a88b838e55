"""The MCAP writer (io.mcapwrite): its bytes, and what the mcap library reads back from them."""

from __future__ import annotations

import hashlib
from io import BytesIO

from mcap.reader import make_reader
from pipe_nav_core.io.mcapwrite import McapWriter, Stream

# sha256 of _small_file() as the writer wrote it before its once-per-file and once-per-chunk
# records were built with mcap.records: the move kept every byte.
SMALL_FILE_SHA256 = "af5e80c0074f2a19ff2d4032cb69d6f2e503139f46139959b7ca1a183c73bb48"


def _small_file() -> bytes:
    f = BytesIO()
    w = McapWriter(f, chunk_size=64)
    w.add_schema(1, "std_msgs/msg/String", "ros2msg", "string data")
    w.add_channel(1, 1, "/a", "cdr", {"offered_qos_profiles": "héllo"})
    w.add_channel(2, 1, "/b", "cdr", {})
    w.write_streams(
        [
            Stream.variable(
                1, [10 * k for k in range(12)], [bytes([k]) * (3 + k) for k in range(12)]
            ),
            Stream.variable(2, [10 * k + 5 for k in range(5)], [b"x" * k for k in range(5)]),
        ]
    )
    w.add_metadata("rosbag2", {"serialized_metadata": "version: 9", "ü": "v"})
    w.add_attachment("welds.csv", "text/csv", b"a,b\n1,2\n", log_time=5, create_time=7)
    w.finish()
    return f.getvalue()


def test_the_bytes_are_those_of_before():
    assert hashlib.sha256(_small_file()).hexdigest() == SMALL_FILE_SHA256


def test_the_mcap_library_reads_everything_back_with_its_crcs():
    reader = make_reader(BytesIO(_small_file()), validate_crcs=True)
    summary = reader.get_summary()
    stats = summary.statistics
    assert (stats.message_count, stats.chunk_count) == (17, len(summary.chunk_indexes))
    assert stats.chunk_count > 1
    assert stats.channel_message_counts == {1: 12, 2: 5}
    assert (stats.message_start_time, stats.message_end_time) == (0, 110)
    assert summary.channels[1].metadata == {"offered_qos_profiles": "héllo"}
    assert [(m.name, m.metadata) for m in reader.iter_metadata()] == [
        ("rosbag2", {"serialized_metadata": "version: 9", "ü": "v"})
    ]
    (att,) = reader.iter_attachments()
    assert (att.name, att.media_type, att.data, att.log_time, att.create_time) == (
        "welds.csv",
        "text/csv",
        b"a,b\n1,2\n",
        5,
        7,
    )
    assert len(list(reader.iter_messages())) == 17
