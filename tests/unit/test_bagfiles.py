"""Finding the MCAP files of a bag path (io.bagfiles.bag_files)."""

from __future__ import annotations

import pytest
from pipe_nav_core.errors import BagError
from pipe_nav_core.io.bagfiles import bag_files


def _metadata(folder, files, storage="mcap", compression=""):
    listed = "".join(f"\n    - {name}" for name in files)
    (folder / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n"
        f"  storage_identifier: {storage}\n"
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
    ("storage", "compression", "match"),
    [("sqlite3", "", "only mcap"), ("mcap", "file", "file-compressed")],
)
def test_unsupported_rosbag2_folders_are_refused(tmp_path, storage, compression, match):
    (tmp_path / "a.mcap").write_bytes(b"")
    _metadata(tmp_path, ["a.mcap"], storage, compression)
    with pytest.raises(BagError, match=match):
        bag_files(tmp_path)


def test_missing_and_empty_paths_are_refused(tmp_path):
    with pytest.raises(BagError, match="no such file"):
        bag_files(tmp_path / "nothing")
    with pytest.raises(BagError, match="neither metadata.yaml nor .mcap"):
        bag_files(tmp_path)
    _metadata(tmp_path, ["gone.mcap"])
    with pytest.raises(BagError, match="none of the files"):
        bag_files(tmp_path)
