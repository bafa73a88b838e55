"""The MCAP record parsing of io.mcaprecords on damaged records: the data section's Schema and
Channel records by our tolerant parser (why not mcap.records), the summary's Chunk Index by
mcap.records, whole or not at all."""

from __future__ import annotations

import mmap
import sys

import numpy as np
import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Schema
from pipe_nav_core.io import read_bag, write_sensor_bag
from pipe_nav_core.io.mcaprecords import OP_CHUNK_INDEX, parse_channel, parse_schema, read_summary
from test_io_support import assert_logs_equal, make_log


def _content(record) -> bytearray:
    builder = RecordBuilder()
    record.write(builder)
    return bytearray(builder.end()[9:])  # without opcode and length


def test_a_field_cut_off_by_the_end_of_its_record_is_an_error():
    content = _content(Schema(id=1, name="a", encoding="ros2msg", data=b"string data"))
    assert parse_schema(bytes(content)).data == b"string data"
    with pytest.raises(ValueError, match="past the end"):
        parse_schema(bytes(content[:-3]))


def test_a_damaged_topic_name_is_read_with_a_replacement_character():
    content = _content(Channel(id=3, schema_id=1, topic="x", message_encoding="cdr", metadata={}))
    content[2 + 2 + 4] = 0xFF  # the topic's one byte: not UTF-8
    ch = parse_channel(bytes(content))
    assert (ch.id, ch.topic, ch.message_encoding) == (3, "\ufffd", "cdr")


def _summary_record(data: bytes, opcode: int) -> int:
    """Byte offset of the content of the first record with ``opcode`` in the summary."""
    footer = len(data) - 8 - 29  # opcode, length, summary start, summary offset start, CRC
    pos = int.from_bytes(data[footer + 9 : footer + 17], "little")
    while data[pos] != opcode:
        pos += 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
    return pos + 9


def test_a_damaged_chunk_index_makes_the_summary_unusable_not_wrong(tmp_path):
    """The summary's Chunk Index records are parsed by mcap.records: one that does not parse
    is no summary (read_summary raises; the bag is read from its data section all the same)."""
    log = make_log(seconds=6.0, seed=3)
    p = tmp_path / "run.mcap"
    write_sensor_bag(p, log, chunk_size=4096)
    s = read_summary(p)
    assert s is not None and len(s.chunk_indexes) > 3 and s.message_count
    assert {ci.compression for ci in s.chunk_indexes} == {"zstd"}
    data = bytearray(p.read_bytes())
    at = _summary_record(bytes(data), OP_CHUNK_INDEX)
    n_map = int.from_bytes(data[at + 32 : at + 36], "little")
    name = at + 36 + n_map + 8 + 4  # the compression name's bytes
    assert data[name : name + 4] == b"zstd"
    data[name] = 0xFF  # not UTF-8
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="damaged ChunkIndex record"):
        read_summary(bad)
    got, rep = read_bag(bad, workers=0)
    assert_logs_equal(got, read_bag(p, workers=0)[0])
    assert not rep.truncated


def _resident_kb(path) -> int:
    """kB of ``path``'s mappings resident in this process (/proc/self/smaps)."""
    total, ours = 0, False
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()
            if len(head) >= 5 and "-" in head[0] and len(head[0]) > 8:  # a mapping's first line
                ours = line.rstrip("\n").endswith(str(path))
            elif ours and head[0] == "Rss:":
                total += int(head[1])
    return total


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/smaps")
@pytest.mark.parametrize("compression", ["", "zstd"])
def test_the_bag_is_read_in_place_and_let_go_of_behind_the_reading(tmp_path, compression):
    """The chunks are read from the mapped file (an uncompressed chunk's records are not
    copied), and the pages before the chunk being read are let go of: while the last batch is
    read, what is resident of the bag is about the chunks in flight, not the file."""
    from pipe_nav_core.io.mcapread import McapScanner
    from pipe_nav_core.sim import simulate

    log = simulate("demo", 0).log
    p = tmp_path / "run.mcap"
    write_sensor_bag(p, log, compression=compression, chunk_size=1 << 16)
    size_kb = p.stat().st_size // 1024  # 14 MB uncompressed, 2 MB zstd
    sc = McapScanner(p, lambda w: None)
    batches = resident = 0
    for batch in sc.batches(workers=1):
        batches += 1
        int(np.asarray(batch.buf).sum())  # every byte of the chunk read
        resident = max(resident, _resident_kb(p))
    assert batches > 10 and not sc.truncated
    assert resident < (0.15 if compression else 0.05) * size_kb
    if not compression:  # the batch's records are the file's mapped bytes, not a copy
        assert isinstance(batch.buf.base, memoryview) and isinstance(batch.buf.base.obj, mmap.mmap)
    assert_logs_equal(read_bag(p)[0], read_bag(p, workers=0)[0])
