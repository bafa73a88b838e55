"""An MCAP file scanned as a stream (read forward, as a zstd-compressed file decompresses)
gives what the same bytes give when mapped: the same messages, warnings, counts of corrupt
messages and ``truncated``, wherever the file is cut or damaged. The mapped scanner is
compared without the summary, which a stream cannot read first. Through zstd, a compressed
file cut short gives a prefix of the messages and says so."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path
from typing import Any
from unittest import mock

import pytest
import zstandard
from hypothesis import example, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer
from pipe_nav_core.errors import BagFormatError
from pipe_nav_core.io import bagforms, mcapread, write_sensor_bag
from pipe_nav_core.io.mcapread import McapScanner
from test_io_support import make_log

Message = tuple[int, int, bytes]  # channel id, log time (ns), payload


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, bytes]:
    """A short run in small chunks, zstd-compressed and not, and without chunks (as the mcap
    library writes it when told not to chunk)."""
    root = tmp_path_factory.mktemp("stream")
    lg = make_log(seconds=6.0, seed=3)
    out = {}
    for name in ("zstd", ""):
        p = root / f"run_{name}.mcap"
        write_sensor_bag(p, lg, compression=name, chunk_size=4096)
        out[name or "plain"] = p.read_bytes()
    loose = io.BytesIO()
    w = Writer(loose, use_chunking=False)
    w.start(profile="ros2", library="test")
    channels: dict[int, int] = {}
    for schema, channel, m in make_reader(io.BytesIO(out["zstd"])).iter_messages():
        if channel.id not in channels:
            sid = w.register_schema(schema.name, schema.encoding, schema.data)
            channels[channel.id] = w.register_channel(channel.topic, "cdr", sid)
        w.add_message(channels[channel.id], m.log_time, m.data, m.publish_time)
    w.finish()
    out["loose"] = loose.getvalue()
    return out


def _scan(sc: McapScanner) -> tuple[list[Message], tuple]:
    msgs: list[Message] = []
    for b in sc.batches():
        for s, n, c, t in zip(b.payload_start.tolist(), b.size.tolist(), b.channel.tolist(),
                              b.log_time.tolist(), strict=True):  # fmt: skip
            msgs.append((c, t, bytes(b.buf[s : s + n])))
    return msgs, (sc.truncated, sc.corrupt_messages, sorted(sc.channels))


def _mapped(path: Path) -> tuple[list[Message], list[str], tuple]:
    warnings: list[str] = []
    with mock.patch.object(mcapread, "read_summary", lambda p: None):
        msgs, state = _scan(McapScanner(path, warnings.append))
    return msgs, warnings, state


def _streamed(path: Path, data: bytes) -> tuple[list[Message], list[str], tuple]:
    warnings: list[str] = []
    msgs, state = _scan(McapScanner(path, warnings.append, stream=io.BytesIO(data).read))
    return msgs, warnings, state


@settings(max_examples=60, deadline=None)
@given(
    form=st.sampled_from(["zstd", "plain", "loose"]),
    cut=st.floats(0.02, 1.0),
    damage=st.one_of(st.none(), st.tuples(st.floats(0.0, 1.0), st.integers(1, 40))),
)
@example(form="zstd", cut=1.0, damage=None)
@example(form="loose", cut=0.5, damage=None)
@example(form="plain", cut=1.0, damage=(0.5, 20))
def test_a_stream_scans_as_the_mapped_file(bags, tmp_path_factory, form, cut, damage):
    data = bytearray(bags[form][: max(9, int(len(bags[form]) * cut))])
    if damage is not None:
        at = 8 + int(damage[0] * (len(data) - 8))
        data[at : at + damage[1]] = b"\x5a" * len(data[at : at + damage[1]])
    p = tmp_path_factory.mktemp("case") / "run.mcap"
    p.write_bytes(bytes(data))
    assert _outcome(_streamed, p, bytes(data)) == _outcome(_mapped, p)


def _outcome(scan: Callable[..., Any], *args: Any) -> Any:
    """What ``scan`` gives, or the error it raises (a damaged record can)."""
    try:
        return scan(*args)
    except ValueError as exc:
        return type(exc), str(exc)


def test_an_intact_stream_reads_every_message(bags, tmp_path):
    p = tmp_path / "run.mcap"
    p.write_bytes(bags["zstd"])
    msgs, warnings, (truncated, corrupt, _) = _streamed(p, bags["zstd"])
    counts = mcapread.read_summary(p).channel_message_counts
    assert len(msgs) == sum(counts.values()) > 500
    assert not warnings and not truncated and not corrupt
    assert msgs == _mapped(p)[0]


def _zstd_scan(data: bytes, path: Path) -> tuple[list[Message], list[str]]:
    warnings: list[str] = []
    stream = bagforms.ZstdStream(io.BytesIO(data), path, warnings.append)
    msgs, _ = _scan(McapScanner(path, warnings.append, stream=stream.read))
    return msgs, warnings


@pytest.mark.parametrize("frames", [1, 3])
def test_a_compressed_file_cut_short_gives_a_prefix_and_says_so(tmp_path, frames):
    write_sensor_bag(tmp_path / "long.mcap", make_log(seconds=60.0, seed=5), chunk_size=4096)
    raw = (tmp_path / "long.mcap").read_bytes()  # zstd's blocks are 128 KiB: many of them
    step = -(-len(raw) // frames)  # rosbag2 writes one frame, other tools several
    packed = b"".join(zstandard.ZstdCompressor().compress(raw[i : i + step])
                      for i in range(0, len(raw), step))  # fmt: skip
    p = tmp_path / "run.mcap.zstd"
    whole, warnings = _zstd_scan(packed, p)
    assert whole == _mapped_bytes(raw, tmp_path) and not warnings
    part, warnings = _zstd_scan(packed[: int(len(packed) * 0.6)], p)
    assert 0 < len(part) < len(whole) and part == whole[: len(part)]
    assert any("the compressed data end early" in w and str(p) in w for w in warnings)
    assert any("before the end of its data section" in w for w in warnings)


def _mapped_bytes(raw: bytes, tmp: Path) -> list[Message]:
    p = tmp / "plain.mcap"
    p.write_bytes(raw)
    return _mapped(p)[0]


def test_a_stream_that_is_not_mcap_is_refused(tmp_path):
    with pytest.raises(BagFormatError, match="not an MCAP file"):
        McapScanner(tmp_path / "x.mcap.zstd", print, stream=io.BytesIO(b"\0" * 64).read)
    with pytest.raises(BagFormatError, match="empty file"):
        McapScanner(tmp_path / "x.mcap.zstd", print, stream=io.BytesIO(b"").read)
