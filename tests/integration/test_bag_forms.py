"""The forms rosbag2 writes a bag in, read as the plain MCAP bag they were made from.

The sample bag is written again as rosbag2 directories by rosbags (a library no one here
wrote): MCAP or sqlite3 storage, each plain, zstd-compressed as whole files and zstd-compressed
message by message. Each must read into the same log and report as the sample itself, give
``pipe-nav info`` the same facts, and smooth into the same bytes. Where ROS 2 is installed,
rosbag2 itself (``ros2 bag convert``) writes the forms too. Damaged forms: a compressed file cut
short gives the part before the cut, a damaged sqlite3 file what is readable around the damage,
a payload that does not decompress is dropped and counted, and a file that is not what its
name says is refused in one line.
"""

from __future__ import annotations

import errno
import os
import shutil
import sqlite3
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from pipe_nav_core.app.cli import main
from pipe_nav_core.bench.rosbag2_forms import COMPRESSIONS, STORAGES, rewrite
from pipe_nav_core.errors import BagError
from pipe_nav_core.io import bag_info, bagforms, read_bag
from pipe_nav_core.io.baginfo import message_count
from pipe_nav_core.io.topics import DEFAULT_TOPICS

SAMPLE = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"
FORMS = [(s, m) for s in STORAGES for m in COMPRESSIONS]


@pytest.fixture(scope="module")
def plain():
    return read_bag(SAMPLE)


@pytest.fixture(scope="module")
def forms(tmp_path_factory):
    root = tmp_path_factory.mktemp("forms")
    return {(s, m): rewrite(SAMPLE, root / f"{s}_{m or 'plain'}", s, m) for s, m in FORMS}


def assert_same_log(a, b):
    for name in ("imu", "odometer", "mag"):
        x, y = getattr(a, name), getattr(b, name)
        for field in x.__dataclass_fields__:
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field), err_msg=name)
    assert a.markers == b.markers


def test_the_forms_are_what_their_names_say(forms):
    names = {k: sorted(p.name for p in d.iterdir()) for k, d in forms.items()}
    assert names[("mcap", "file")] == ["mcap_file.mcap.zstd", "metadata.yaml"]
    assert names[("sqlite3", "")] == ["metadata.yaml", "sqlite3_plain.db3"]
    with open(forms[("mcap", "message")] / "mcap_message.mcap", "rb") as f:
        _, _, first = next(make_reader(f).iter_messages())
    assert first.data[:4] == b"\x28\xb5\x2f\xfd"  # a zstd frame, not CDR


@pytest.mark.parametrize(("storage", "mode"), FORMS)
def test_every_form_reads_as_the_plain_bag(plain, forms, storage, mode):
    log, report = read_bag(forms[(storage, mode)])
    assert_same_log(log, plain[0])
    assert report.warnings == plain[1].warnings
    assert report.counts == plain[1].counts
    assert report.imu_noise_declared == plain[1].imu_noise_declared
    assert not report.truncated


@pytest.mark.parametrize(("storage", "mode"), FORMS)
def test_info_of_every_form(forms, storage, mode):
    want, got = bag_info(SAMPLE), bag_info(forms[(storage, mode)])
    assert got.message_count == want.message_count
    for topic, t in want.topics.items():
        g = got.topics[topic]
        assert (g.msgtype, g.count, g.start, g.end) == (t.msgtype, t.count, t.start, t.end)


def test_the_message_count_from_summaries_or_metadata(forms):
    """What decides whether the first pass runs while the bag is read."""
    want = message_count(SAMPLE)
    assert want == sum(t.count for t in bag_info(SAMPLE).topics.values())
    assert {message_count(d) for d in forms.values()} == {want}
    assert message_count(forms[("sqlite3", "")] / "metadata.yaml") == want  # as bag_layout
    assert message_count(forms[("sqlite3", "")] / "sqlite3_plain.db3") is None  # no metadata


def test_a_message_compressed_file_without_its_metadata(plain, forms, tmp_path):
    alone = tmp_path / "copied.mcap"
    shutil.copy(forms[("mcap", "message")] / "mcap_message.mcap", alone)
    assert_same_log(read_bag(alone)[0], plain[0])


def _smoothed_csv(bag: Path, out: Path) -> bytes:
    assert main(["smooth", str(bag), "--out", f"{out}/", "--quiet"]) == 0
    (csv,) = out.glob("*_centerline.csv")
    return csv.read_bytes()


def test_the_forms_smooth_into_the_same_centreline(forms, tmp_path):
    want = _smoothed_csv(SAMPLE, tmp_path / "plain")
    for form in (("sqlite3", "message"), ("mcap", "file")):
        assert _smoothed_csv(forms[form], tmp_path / "_".join(form)) == want, form


def test_a_compressed_file_cut_short_gives_what_came_before(plain, forms, tmp_path):
    bag = tmp_path / "cut"
    shutil.copytree(forms[("mcap", "file")], bag)
    f = bag / "mcap_file.mcap.zstd"
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    log, report = read_bag(bag)
    assert 0 < len(log.imu) < len(plain[0].imu)
    np.testing.assert_array_equal(log.imu.t, plain[0].imu.t[: len(log.imu)])
    assert report.truncated
    assert any("end early or are damaged" in w for w in report.warnings)


def test_a_damaged_sqlite3_file_gives_what_is_readable_around_the_damage(plain, forms, tmp_path):
    """A damaged page loses the messages on it, not the rest of the file: the batches
    before it and after it are read, and the one holding it up to the damage."""
    bag = tmp_path / "damaged"
    shutil.copytree(forms[("sqlite3", "")], bag)
    f = bag / "sqlite3_plain.db3"
    data = bytearray(f.read_bytes())
    page = int(0.5 * len(data)) // 4096 * 4096  # a page of messages in the middle
    data[page : page + 4096] = b"\xa5" * 4096
    f.write_bytes(bytes(data))
    log, report = read_bag(bag)
    t, want = log.imu.t, plain[0].imu.t
    lost = len(want) - len(t)
    assert 0 < lost < 30  # a 4 KiB page holds about ten of the sample's messages
    gap = int(np.argmax(t != want[: len(t)]))  # the first sample after the damage
    assert gap > 0 and t[gap - 1] == want[gap - 1]
    np.testing.assert_array_equal(t[gap:], want[gap + lost :])  # the rest, to the end
    assert report.truncated
    (warning,) = [w for w in report.warnings if "are unreadable" in w]
    assert str(f) in warning and "the rest was read" in warning


def test_a_payload_stored_as_text_reads_as_its_bytes(plain, forms, tmp_path, monkeypatch):
    """SQLite's concatenation counts a text value's characters, not its bytes: the batch
    holding one is read row by row, and the log is the plain bag's."""
    bag = tmp_path / "text"
    shutil.copytree(forms[("sqlite3", "")], bag)
    db = sqlite3.connect(bag / "sqlite3_plain.db3")
    db.execute("UPDATE messages SET data = CAST(data AS TEXT) WHERE id = 700")
    db.commit()
    db.close()
    by_rows: list[int] = []
    rows = bagforms.Db3Scanner._rows

    def spy(self, first, last):
        by_rows.append(first)
        return rows(self, first, last)

    monkeypatch.setattr(bagforms.Db3Scanner, "_rows", spy)
    log, report = read_bag(bag)
    assert_same_log(log, plain[0])
    assert by_rows == [1]  # the first batch only (ids 1 to DB3_BATCH_ROWS)


def test_a_sqlite3_file_whose_ids_are_not_its_rowids(plain, forms, tmp_path):
    """A foreign writer's messages table without rosbag2's INTEGER PRIMARY KEY (its ids
    not the rowids, the rows stored out of id order) reads as the plain bag, row by row."""
    bag = tmp_path / "foreign"
    shutil.copytree(forms[("sqlite3", "")], bag)
    db = sqlite3.connect(bag / "sqlite3_plain.db3")
    db.executescript(
        "CREATE TABLE m2 (id INTEGER, topic_id INTEGER, timestamp INTEGER, data BLOB);"
        "INSERT INTO m2 SELECT id, topic_id, timestamp, data FROM messages ORDER BY id DESC;"
        "DROP TABLE messages; ALTER TABLE m2 RENAME TO messages;"
    )
    db.close()
    log, report = read_bag(bag)  # row by row, in id order
    assert_same_log(log, plain[0])
    assert not report.truncated


def test_a_sqlite3_read_left_early_lets_its_read_ahead_thread_go(forms):
    sc = bagforms.Db3Scanner(forms[("sqlite3", "")] / "sqlite3_plain.db3", print)
    batches = sc.batches()
    first = next(batches)  # the next range is being read ahead now
    assert 0 < len(first) <= bagforms.DB3_BATCH_ROWS
    assert any(t.name.startswith("db3-read") for t in threading.enumerate())
    batches.close()
    assert not any(t.name.startswith("db3-read") for t in threading.enumerate())


def test_a_payload_that_does_not_decompress_is_dropped_and_counted(
    plain, forms, tmp_path, monkeypatch
):
    bag = tmp_path / "bad_frame"
    shutil.copytree(forms[("sqlite3", "message")], bag)
    db = sqlite3.connect(bag / "sqlite3_message.db3")
    (tid,) = db.execute("SELECT id FROM topics WHERE name = ?", (DEFAULT_TOPICS.imu,)).fetchone()
    (mid, data) = db.execute(
        "SELECT id, data FROM messages WHERE topic_id = ? ORDER BY id LIMIT 1 OFFSET 500", (tid,)
    ).fetchone()
    db.execute("UPDATE messages SET data = ? WHERE id = ?", (data[:4] + b"\0" * 8, mid))
    db.commit()
    db.close()
    one_by_one = _frames_one_by_one(monkeypatch)
    log, report = read_bag(bag)
    assert len(log.imu) == len(plain[0].imu) - 1
    assert sum(report.skipped_by_topic[DEFAULT_TOPICS.imu].values()) == 1
    assert one_by_one  # the batch holding the bad frame, frame by frame
    one_by_one.clear()
    assert_same_log(read_bag(forms[("sqlite3", "message")])[0], plain[0])
    assert not one_by_one  # every batch of good frames at once


def _frames_one_by_one(monkeypatch) -> list[int]:
    """The frames bagforms.unpacked decompresses one at a time (after it has tried the
    batch's frames at once), as they are taken."""
    taken: list[int] = []
    frame = bagforms._frame

    def spy(d, error, p):
        taken.append(len(p))
        return frame(d, error, p)

    monkeypatch.setattr(bagforms, "_frame", spy)
    return taken


@pytest.mark.parametrize(
    ("name", "content", "match"),
    [("run.db3", b"not a database" * 100, "not a readable rosbag2 sqlite3 file"),
     ("run.mcap.zstd", b"not zstd" * 100, "not a zstd-compressed file")],
)  # fmt: skip
def test_a_file_that_is_not_its_form_is_refused_in_one_line(tmp_path, capsys, name, content,
                                                            match):  # fmt: skip
    f = tmp_path / name
    f.write_bytes(content)
    with pytest.raises(BagError, match=match):
        read_bag(f)
    assert main(["smooth", str(f), "--out", f"{tmp_path}/o/", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(f) in err[0] and match in err[0]


ROS2 = shutil.which("ros2")


@pytest.mark.skipif(ROS2 is None, reason="ros2 is not on PATH (source .ci/ros-env)")
def test_the_forms_rosbag2_itself_writes(plain, tmp_path):
    """``ros2 bag convert`` writes the sample as rosbag2 does: its MCAP defaults, its fastwrite
    preset (no chunks), zstd file and message compression and sqlite3. Each reads as the
    sample; rosbag2's message compression may drop messages it cannot compress in time, so
    there every message the file holds is read."""
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(SAMPLE, src / "sample.mcap")
    from pipe_nav_core.io import write_rosbag2_metadata

    write_rosbag2_metadata(src / "sample.mcap")
    forms = {
        "default": "storage_id: mcap",
        "fastwrite": "storage_id: mcap\n  storage_preset_profile: fastwrite",
        "file": "storage_id: mcap\n  compression_mode: file\n  compression_format: zstd",
        "message": "storage_id: mcap\n  compression_mode: message\n  compression_format: zstd",
        "sqlite3": "storage_id: sqlite3",
    }
    spec = "output_bags:\n" + "".join(
        f"- uri: {tmp_path / name}\n  all_topics: true\n  {opts}\n" for name, opts in forms.items()
    )
    (tmp_path / "convert.yaml").write_text(spec)
    subprocess.run([ROS2, "bag", "convert", "-i", str(src), "-o", str(tmp_path / "convert.yaml")],
                   check=True, capture_output=True, timeout=120)  # fmt: skip
    for name in forms:
        log, report = read_bag(tmp_path / name)
        if name != "message":
            assert_same_log(log, plain[0])
            assert report.warnings == plain[1].warnings
            continue
        (f,) = (tmp_path / name).glob("*.mcap")
        with open(f, "rb") as fh:
            held = sum(1 for _ in make_reader(fh).iter_messages(topics=[DEFAULT_TOPICS.imu]))
        # every message the file holds is read: rosbag2 compresses the messages in a thread of
        # its own, and under load it holds fewer of them (74 % of the sample's IMU messages
        # with two benches beside it) and writes some a second or more after their neighbours
        # (their log times as late as their stamps: kept and sorted into place)
        assert len(log.imu) == held > 0.5 * len(plain[0].imu)
        assert DEFAULT_TOPICS.imu not in report.skipped_by_topic


def test_a_full_temporary_folder_is_named(forms, tmp_path, monkeypatch, capsys):
    from pipe_nav_core.io import bagforms

    def full(src, out, length):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(bagforms.shutil, "copyfileobj", full)
    bag = forms[("sqlite3", "file")] / "sqlite3_file.db3.zstd"  # an MCAP one is streamed
    with pytest.raises(BagError, match=r"cannot decompress it into .*No space left on device"):
        read_bag(bag)
    assert main(["smooth", str(bag), "--out", f"{tmp_path}/o/", "--quiet"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"pipe-nav: error: {bag}: cannot decompress it into")
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
