"""The pooled bag reader (chunks decompressed, CRC-checked and located by worker threads ahead
of the decoding) gives exactly what the serial reader gives: the same SensorLog and the same
BagReport (counts, skip reasons, warnings in the same order), on clean, damaged and
foreign-written bags. By default chunks of every compression go to the pool; every test also
reads with only the zstd chunks pooled, so that chunks unpacked by the consumer between pooled
ones go through the same machinery."""

from __future__ import annotations

import os
import threading
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from pipe_nav_core.errors import BagError
from pipe_nav_core.io import (
    BagReport,
    bagread,
    iter_bag,
    mcapchunks,
    mcapread,
    read_bag,
    write_sensor_bag,
)
from pipe_nav_core.io import rosmsg as R
from pipe_nav_core.io.bagread import READ_WORKERS_ENV, read_workers
from pipe_nav_core.io.mcapread import McapScanner, read_summary
from pipe_nav_core.io.rosmsg import jazzy_typestore
from pipe_nav_core.io.stamps import sec_to_ns_scalar
from pipe_nav_core.types import SensorLog
from test_io_support import log_messages, make_log, write_rosbags_dir

SMALL_CHUNK = 16 * 1024  # dozens of chunks: more than the pool reads ahead
POOLS = (1, 2, 3)
ONLY_ZSTD = frozenset({"zstd"})


@pytest.fixture(scope="module")
def log() -> SensorLog:
    lg = make_log(seconds=30.0, seed=4)
    lg.imu.gyro[[5, 700, 701]] = np.nan  # counted as nan, in two different chunks
    lg.odometer.speed[40] = np.inf
    return lg


def _assert_same(a: SensorLog, b: SensorLog) -> None:
    for name, fields in (
        ("imu", ("t", "gyro", "accel")),
        ("odometer", ("t", "distance", "speed")),
        ("mag", ("t", "field")),
    ):
        for f in fields:
            x, y = getattr(getattr(a, name), f), getattr(getattr(b, name), f)
            assert x.dtype == y.dtype and x.shape == y.shape, (name, f)
            assert np.array_equal(x, y), (name, f)
    assert a.markers == b.markers


def _read_all_ways(path: Path) -> tuple[SensorLog, BagReport]:
    """read_bag serially and with every pool size, with the default pooled compressions and
    with only zstd pooled; asserts they agree; the serial result."""
    ref_log, ref_rep = read_bag(path, workers=0)
    for pooled in (mcapread.POOLED_COMPRESSIONS, ONLY_ZSTD):
        with mock.patch.object(mcapread, "POOLED_COMPRESSIONS", pooled):
            for w in POOLS:
                got_log, got_rep = read_bag(path, workers=w)
                _assert_same(ref_log, got_log)
                assert got_rep == ref_rep, (w, pooled)
    return ref_log, ref_rep


def _chunks(path: Path) -> int:
    s = read_summary(path)
    assert s is not None
    return len(s.chunk_indexes)


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
def test_multi_chunk_bag_reads_the_same_with_a_pool(tmp_path, log, compression):
    p = tmp_path / "run.mcap"
    write_sensor_bag(p, log, compression=compression, chunk_size=SMALL_CHUNK)
    assert _chunks(p) > 2 * max(POOLS) + 1  # the look-ahead limit is reached
    got, rep = _read_all_ways(p)
    assert len(got.imu) == len(log.imu) - 3
    assert rep.skipped_by_topic["/imu/data"] == {"nan": 3}
    assert rep.skipped_by_topic["/odom/wheel"] == {"nan": 1}
    assert rep.imu_noise_declared
    assert not rep.truncated


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_corrupt_chunks_read_the_same_with_a_pool(tmp_path, log, compression):
    p = tmp_path / "run.mcap"
    write_sensor_bag(p, log, compression=compression, chunk_size=SMALL_CHUNK)
    s = read_summary(p)
    data = bytearray(p.read_bytes())
    for k in (3, 4, len(s.chunk_indexes) - 2):  # two in a row and one near the end
        ci = s.chunk_indexes[k]
        mid = ci.chunk_start_offset + ci.chunk_length // 2
        data[mid : mid + 64] = bytes(64)
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(data))
    got, rep = _read_all_ways(bad)
    assert rep.truncated
    assert sum(1 for w in rep.warnings if "is unreadable" in w) == 3
    lost = sum(r.get("corrupt_chunk", 0) for r in rep.skipped_by_topic.values())
    n_in = len(log.imu) + len(log.odometer) + len(log.mag) + len(log.markers) - 4  # 4 NaN
    assert lost > 0 and len(got.imu) + len(got.odometer) + len(got.mag) + len(got.markers) == (
        n_in - lost
    )


@pytest.mark.parametrize(
    ("fraction", "in_data"), [(0.3, True), (0.55, True), (0.85, True), (0.999, False)]
)
def test_truncated_bags_read_the_same_with_a_pool(tmp_path, log, fraction, in_data):
    """Cut files have no summary: channels come from the records read ahead. A cut in the
    summary loses nothing."""
    p = tmp_path / "run.mcap"
    write_sensor_bag(p, log, chunk_size=SMALL_CHUNK)
    data = p.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    assert read_summary(cut) is None
    got, rep = _read_all_ways(cut)
    assert rep.truncated == in_data
    assert 0 < len(got.imu) <= len(log.imu)
    assert (len(got.imu) < len(log.imu) - 3) == in_data


def test_cut_inside_the_only_chunk_reads_the_same_with_a_pool(tmp_path, log):
    p = tmp_path / "one.mcap"
    write_sensor_bag(p, log, chunk_size=1 << 30)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    got, rep = _read_all_ways(cut)
    assert any("recovered" in w for w in rep.warnings)
    assert 0 < len(got.imu) < len(log.imu)


def _library_bag(path: Path, log: SensorLog, compression: str) -> Path:
    """A bag by the mcap library's writer: Schema and Channel records inside the chunks."""
    from mcap.writer import CompressionType, Writer
    from pipe_nav_core.io.bagwrite import message_definition

    ts = jazzy_typestore()
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=8192, compression=getattr(CompressionType, compression))
        w.start(profile="ros2", library="test")
        chans: dict[str, int] = {}
        for topic, typename, ns, msg in log_messages(log):
            if topic not in chans:
                sid = w.register_schema(typename, "ros2msg", message_definition(typename).encode())
                chans[topic] = w.register_channel(topic, "cdr", sid)
            w.add_message(chans[topic], ns, bytes(ts.serialize_cdr(msg, typename)), ns)
        w.finish()
    return path


@pytest.mark.parametrize("compression", ["ZSTD", "LZ4"])
def test_library_written_bags_with_inline_channels_read_the_same(tmp_path, compression):
    lg = make_log(seconds=12.0, seed=2)
    p = _library_bag(tmp_path / "lib.mcap", lg, compression)
    got, _ = _read_all_ways(p)
    assert len(got.imu) == len(lg.imu)
    # without the summary the channels are only known from inside the chunks, where the
    # consumer meets them later than the workers do
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(p.read_bytes()[: int(p.stat().st_size * 0.8)])
    assert read_summary(cut) is None
    got, rep = _read_all_ways(cut)
    assert rep.truncated and 0 < len(got.imu) < len(lg.imu)


def test_fallback_decoding_and_wrong_types_read_the_same(tmp_path):
    """Big-endian and broken payloads (left to the consumer's thread) and a topic carrying
    the wrong type give the same counts and warnings."""
    ts = jazzy_typestore()
    types = R.rosbags_types()
    msgs = []
    for i in range(300):
        t = 5.0 + 0.01 * i
        m = R.imu_to_msg(types, t, [float(i), 0.5, -0.5], [0.0, 0.0, 9.8])
        if i % 7 == 1:
            raw = bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu", little_endian=False))
        elif i in (10, 122):
            raw = bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu"))[:30]  # cut short
        else:
            raw = bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu"))
        msgs.append(("/imu/data", "sensor_msgs/msg/Imu", sec_to_ns_scalar(t), raw))
        msgs.append(("/odom/wheel", "sensor_msgs/msg/Imu", sec_to_ns_scalar(t), raw))
    got, rep = _read_all_ways(write_rosbags_dir(tmp_path / "rb", msgs))
    assert rep.skipped_by_topic["/imu/data"] == {"bad_cdr": 2}
    assert rep.skipped_by_topic["/odom/wheel"] == {"unknown_type": 300}
    assert any("/odom/wheel: carries sensor_msgs/msg/Imu" in w for w in rep.warnings)
    assert len(got.imu) == 298


def test_random_damage_reads_the_same_with_a_pool(tmp_path):
    """Wherever a file is damaged, the pooled reader fails or succeeds exactly as the serial."""
    lg = make_log(seconds=8.0, seed=9)
    p = tmp_path / "run.mcap"
    write_sensor_bag(p, lg, chunk_size=4096)
    data = p.read_bytes()
    rng = np.random.default_rng(11)
    for k in range(12):
        bad = bytearray(data)
        at, n = int(rng.integers(8, len(data) - 64)), int(rng.integers(1, 65))
        bad[at : at + n] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        q = tmp_path / f"bad{k}.mcap"
        q.write_bytes(bytes(bad))
        outcomes = []
        for w in (0, 2):
            try:
                lg_w, rep_w = read_bag(q, workers=w)
                outcomes.append(("ok", lg_w, rep_w))
            except (BagError, ValueError) as exc:
                outcomes.append(("error", type(exc), str(exc)))
        assert outcomes[0][0] == outcomes[1][0], k
        if outcomes[0][0] == "ok":
            _assert_same(outcomes[0][1], outcomes[1][1])
            assert outcomes[0][2] == outcomes[1][2], k
        else:
            assert outcomes[0][1:] == outcomes[1][1:], k


def test_streaming_reads_the_same_with_a_pool(tmp_path, log):
    p = tmp_path / "run.mcap"
    write_sensor_bag(p, log, chunk_size=SMALL_CHUNK)
    reps = [BagReport(), BagReport()]
    serial = list(iter_bag(p, chunk_seconds=5.0, report=reps[0], workers=0))
    pooled = list(iter_bag(p, chunk_seconds=5.0, report=reps[1], workers=2))
    assert len(serial) == len(pooled) >= 6
    for a, b in zip(serial, pooled, strict=True):
        _assert_same(a, b)
    assert reps[0] == reps[1]


def _pool_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("mcap-chunk")]


def test_the_pool_works_in_its_own_threads_and_goes_away(tmp_path, log, monkeypatch):
    p = tmp_path / "run.mcap"
    write_sensor_bag(p, log, chunk_size=SMALL_CHUNK)
    seen: list[str] = []
    unpack = mcapchunks.unpack_chunk

    def spy(content: bytes) -> bytes:
        seen.append(threading.current_thread().name)
        return unpack(content)

    monkeypatch.setattr(mcapchunks, "unpack_chunk", spy)
    batches = list(McapScanner(p, lambda _: None).batches(2))
    assert len(batches) == len(seen) == _chunks(p)
    assert all(name.startswith("mcap-chunk") for name in seen)
    assert not _pool_threads()
    here = {threading.current_thread().name}
    seen.clear()
    assert len(list(McapScanner(p, lambda _: None).batches(0))) == len(batches)
    assert set(seen) == here  # serially: in this thread
    # lz4 and stored chunks too: their CRC check costs as much as lz4's decompression
    for compression in ("lz4", ""):
        q = tmp_path / f"{compression or 'none'}.mcap"
        write_sensor_bag(q, log, compression=compression, chunk_size=SMALL_CHUNK)
        seen.clear()
        assert len(list(McapScanner(q, lambda _: None).batches(2))) == _chunks(q)
        assert len(seen) == _chunks(q) and all(name.startswith("mcap-chunk") for name in seen)
    # a consumer that stops early (an abandoned stream) leaves no worker behind either (the
    # checks run batch by batch, so that the first time chunk comes before the end is read)
    monkeypatch.setattr(bagread, "CHECK_MESSAGES", 1)
    it = iter_bag(p, chunk_seconds=2.0, workers=2)
    next(it)
    assert _pool_threads()
    it.close()
    assert not _pool_threads()


def test_read_workers_from_the_argument_or_the_environment(monkeypatch):
    monkeypatch.delenv(READ_WORKERS_ENV, raising=False)
    assert read_workers(0) == 0 and read_workers(3) == 3
    assert read_workers() == (1 if (os.cpu_count() or 1) >= 2 else 0)
    # with a busy thread beside the reading (the first pass), only where a core is left
    for cores, want in ((1, 0), (2, 0), (3, 1), (8, 1)):
        monkeypatch.setattr(os, "cpu_count", lambda n=cores: n)
        assert read_workers(beside=1) == want, cores
        assert read_workers() == min(cores - 1, 1), cores
    monkeypatch.undo()
    monkeypatch.setenv(READ_WORKERS_ENV, "0")
    assert read_workers() == 0
    monkeypatch.setenv(READ_WORKERS_ENV, "2")
    assert read_workers(beside=1) == 2  # the environment wins
    monkeypatch.setenv(READ_WORKERS_ENV, "0")
    assert read_workers(2) == 2  # the argument wins
    monkeypatch.setenv(READ_WORKERS_ENV, "two")
    with pytest.raises(ValueError, match=f"^{READ_WORKERS_ENV}='two': not a whole number") as ei:
        read_workers()
    assert "\n" not in str(ei.value)
    with pytest.raises(ValueError, match="whole number >= 0, got -1"):
        read_workers(-1)
    with pytest.raises(ValueError, match="got 1.5"):
        read_bag("no-such-bag.mcap", workers=1.5)  # type: ignore[arg-type]
