"""The MCAP record parsing of io.mcapread on damaged records (why it is not mcap.records)."""

from __future__ import annotations

import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Schema
from pipe_nav_core.io.mcapread import parse_channel, parse_schema


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
