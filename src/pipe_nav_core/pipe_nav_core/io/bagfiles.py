"""Finding the files of a bag path, in reading order, and the form rosbag2 wrote them in.

A bag is a single file or a rosbag2 directory. A directory with ``metadata.yaml`` is read in
the order its ``relative_file_paths`` list; a directory without it, its ``*.mcap`` files (else
its ``*.db3`` files) in name order. Besides the MCAP files of rosbag2's default storage, the
forms rosbag2 also writes are read (:mod:`.bagforms`): its sqlite3 storage (``.db3``, the
default before Iron) and its zstd compression of whole files (``compression_mode: file``,
``.mcap.zstd`` / ``.db3.zstd``); its compression of each message (``compression_mode:
message``) is found message by message, so it needs no metadata. Kept apart from the reader
because :mod:`.baginfo` and the IMU-noise lookup need the same list without reading any
message.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any

from pipe_nav_core.errors import BagError

STORAGES = ("mcap", "sqlite3")
STORAGE_SUFFIX = {".mcap": "mcap", ".db3": "sqlite3"}
FILE_COMPRESSION_SUFFIX = ".zstd"  # rosbag2's zstd compression of a whole file


@dataclass(frozen=True)
class BagFile:
    """One file of a bag: its ``path``, its ``storage`` (``mcap`` or ``sqlite3``) and whether
    rosbag2 compressed the whole file with zstd (``compressed``; its storage is then that of
    the name without ``.zstd``)."""

    path: Path
    storage: str
    compressed: bool = False

    @property
    def plain_mcap(self) -> bool:
        """An MCAP file as it is (its summary and chunks readable in place)."""
        return self.storage == "mcap" and not self.compressed


def file_form(path: Path) -> BagFile:
    """The storage and file compression of one bag file, from its name (``x.mcap``,
    ``x.db3``, ``x.mcap.zstd``, ``x.db3.zstd``); a name without a known suffix is taken as
    MCAP (its magic bytes tell the reader)."""
    compressed = path.name.lower().endswith(FILE_COMPRESSION_SUFFIX)
    inner = path.with_suffix("") if compressed else path
    return BagFile(path, STORAGE_SUFFIX.get(inner.suffix.lower(), "mcap"), compressed)


def bag_layout(path: str | os.PathLike[str]) -> list[BagFile]:
    """The files of a bag in reading order, each with its form (raises BagError with a
    one-line reason)."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such file or directory")
    if p.is_file() and p.name == "metadata.yaml":
        p = p.parent
    if p.is_file():
        return [file_form(p)]
    meta = p / "metadata.yaml"
    if meta.is_file():
        return _from_metadata(p, meta)
    for suffix in STORAGE_SUFFIX:
        files = sorted(x for x in p.iterdir() if x.suffix == suffix and x.is_file())
        if files:
            return [file_form(f) for f in files]
    raise BagError(f"{p}: directory has neither metadata.yaml nor .mcap or .db3 files")


def rosbag2_info(meta: Path) -> Any:
    """The ``rosbag2_bagfile_information`` mapping of a rosbag2 ``metadata.yaml`` (raises what
    reading or parsing it raises)."""
    from ruamel.yaml import YAML

    return YAML(typ="safe").load(meta.read_text())["rosbag2_bagfile_information"]


def _from_metadata(p: Path, meta: Path) -> list[BagFile]:
    try:
        info = rosbag2_info(meta)
        storage = str(info.get("storage_identifier", "mcap"))
        names = [PurePath(str(x)).name for x in info.get("relative_file_paths", [])]
        mode = str(info.get("compression_mode", "") or "").lower()
        fmt = str(info.get("compression_format", "") or "").lower()
    except Exception as exc:
        raise BagError(f"{meta}: unreadable rosbag2 metadata ({exc.__class__.__name__})") from None
    if storage not in STORAGES:
        raise BagError(
            f"{p}: storage '{storage}' is not supported, only {' and '.join(STORAGES)} "
            "(convert with: ros2 bag convert)"
        )
    if mode not in ("", "none") and fmt != "zstd":
        raise BagError(
            f"{p}: compression format '{fmt}' is not supported, only zstd "
            "(convert with: ros2 bag convert)"
        )
    compressed = mode == "file"
    files = [BagFile(p / n, storage, compressed) for n in names]
    if not any(f.path.is_file() for f in files):
        raise BagError(f"{p}: none of the files listed in metadata.yaml exist")
    return files


def bag_stem(path: str | os.PathLike[str]) -> str:
    """A bag's name for the files made from it: a directory's name, a file's name without its
    suffixes (``run.mcap``, ``run.db3``, ``run.mcap.zstd`` -> ``run``)."""
    p = Path(os.fspath(path).rstrip("/") or "/")
    if p.is_dir():
        return p.name
    name = p.name
    if name.lower().endswith(FILE_COMPRESSION_SUFFIX):
        name = name[: -len(FILE_COMPRESSION_SUFFIX)]
    return Path(name).stem


def bag_files(path: str | os.PathLike[str]) -> list[Path]:
    """The files of a bag, in reading order (raises BagError with a one-line reason)."""
    return [f.path for f in bag_layout(path)]
