"""Finding the files of a bag path and their forms (io.bagfiles.bag_files, bag_layout)."""

from __future__ import annotations

import pytest
from pipe_nav_core.errors import BagError
from pipe_nav_core.io.bagfiles import BagFile, bag_files, bag_layout, bag_stem


def _metadata(folder, files, storage="mcap", compression="", fmt=""):
    listed = "".join(f"\n    - {name}" for name in files)
    (folder / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n"
        f"  storage_identifier: {storage}\n"
        f"  compression_format: '{fmt}'\n"
        f"  compression_mode: '{compression}'\n"
        f"  relative_file_paths:{listed}\n"
    )


def test_a_file_is_its_own_bag(tmp_path):
    f = tmp_path / "run.mcap"
    f.write_bytes(b"")
    assert bag_files(f) == [f]


def test_metadata_order_wins_over_name_order_and_names_the_folder(tmp_path):
    for name in ("a.mcap", "b.mcap"):
        (tmp_path / name).write_bytes(b"")
    _metadata(tmp_path, ["b.mcap", "a.mcap"])
    want = [tmp_path / "b.mcap", tmp_path / "a.mcap"]
    assert bag_files(tmp_path) == want
    assert bag_files(tmp_path / "metadata.yaml") == want


def test_without_metadata_the_mcap_files_in_name_order(tmp_path):
    for name in ("run_1.mcap", "run_0.mcap", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert bag_files(tmp_path) == [tmp_path / "run_0.mcap", tmp_path / "run_1.mcap"]


@pytest.mark.parametrize(
    ("name", "storage", "compressed"),
    [("run.mcap", "mcap", False), ("run.db3", "sqlite3", False),
     ("run.mcap.zstd", "mcap", True), ("run.db3.zstd", "sqlite3", True),
     ("run.bin", "mcap", False)],
)  # fmt: skip
def test_a_file_alone_has_the_form_its_name_says(tmp_path, name, storage, compressed):
    f = tmp_path / name
    f.write_bytes(b"")
    assert bag_layout(f) == [BagFile(f, storage, compressed)]
    assert bag_layout(f)[0].plain_mcap == (storage == "mcap" and not compressed)


def test_the_forms_rosbag2_writes_come_from_its_metadata(tmp_path):
    (tmp_path / "a_0.db3.zstd").write_bytes(b"")
    _metadata(tmp_path, ["a_0.db3.zstd"], "sqlite3", "FILE", "zstd")
    assert bag_layout(tmp_path) == [BagFile(tmp_path / "a_0.db3.zstd", "sqlite3", True)]
    _metadata(tmp_path, ["a_0.db3.zstd"], "sqlite3", "MESSAGE", "zstd")  # found per message
    assert bag_layout(tmp_path) == [BagFile(tmp_path / "a_0.db3.zstd", "sqlite3", False)]


def test_without_metadata_the_db3_files_when_there_is_no_mcap_file(tmp_path):
    for name in ("b.db3", "a.db3"):
        (tmp_path / name).write_bytes(b"")
    assert bag_files(tmp_path) == [tmp_path / "a.db3", tmp_path / "b.db3"]


@pytest.mark.parametrize(
    ("storage", "compression", "fmt", "match"),
    [("rosbag_v2", "", "", "storage 'rosbag_v2' is not supported, only mcap and sqlite3"),
     ("mcap", "file", "lz4", "compression format 'lz4' is not supported, only zstd")],
)  # fmt: skip
def test_unsupported_rosbag2_folders_are_refused(tmp_path, storage, compression, fmt, match):
    (tmp_path / "a.mcap").write_bytes(b"")
    _metadata(tmp_path, ["a.mcap"], storage, compression, fmt)
    with pytest.raises(BagError, match=match):
        bag_files(tmp_path)


def test_missing_and_empty_paths_are_refused(tmp_path):
    with pytest.raises(BagError, match="no such file"):
        bag_files(tmp_path / "nothing")
    with pytest.raises(BagError, match="neither metadata.yaml nor .mcap or .db3"):
        bag_files(tmp_path)
    _metadata(tmp_path, ["gone.mcap"])
    with pytest.raises(BagError, match="none of the files"):
        bag_files(tmp_path)


def test_a_bags_stem_names_the_files_made_from_it(tmp_path):
    for name in ("run.mcap", "run.db3", "run.mcap.zstd", "run.db3.zstd"):
        (tmp_path / name).write_bytes(b"")
        assert bag_stem(tmp_path / name) == "run"
    folder = tmp_path / "rosbag2_2026_12_05-10.30"
    folder.mkdir()
    assert bag_stem(folder) == bag_stem(f"{folder}/") == "rosbag2_2026_12_05-10.30"
