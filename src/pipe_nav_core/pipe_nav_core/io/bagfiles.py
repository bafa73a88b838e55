"""Finding the MCAP files of a bag path, in reading order.

A bag is a single ``.mcap`` file or a rosbag2 directory. A directory with ``metadata.yaml``
is read in the order its ``relative_file_paths`` list (only the mcap storage, not
file-compressed); a directory without it, its ``*.mcap`` files in name order. Kept apart from
the reader because :mod:`.baginfo` and the IMU-noise lookup need the same list without reading
any message.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePath

from pipe_nav_core.errors import BagError


def bag_files(path: str | os.PathLike[str]) -> list[Path]:
    """The MCAP files of a bag, in reading order (raises BagError with a one-line reason)."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such file or directory")
    if p.is_file() and p.name == "metadata.yaml":
        p = p.parent
    if p.is_file():
        return [p]
    meta = p / "metadata.yaml"
    if meta.is_file():
        try:
            from ruamel.yaml import YAML

            doc = YAML(typ="safe").load(meta.read_text())
            info = doc["rosbag2_bagfile_information"]
            storage = str(info.get("storage_identifier", "mcap"))
            names = [PurePath(str(x)).name for x in info.get("relative_file_paths", [])]
            compression = str(info.get("compression_mode", "") or "").lower()
        except Exception as exc:
            raise BagError(
                f"{meta}: unreadable rosbag2 metadata ({exc.__class__.__name__})"
            ) from None
        if storage != "mcap":
            raise BagError(
                f"{p}: storage '{storage}' is not supported, only mcap "
                "(convert with: ros2 bag convert)"
            )
        if compression == "file":
            raise BagError(
                f"{p}: file-compressed rosbag2 bags are not supported (decompress first)"
            )
        files = [p / n for n in names]
        present = [f for f in files if f.is_file()]
        if not present:
            raise BagError(f"{p}: none of the files listed in metadata.yaml exist")
        return files
    files = sorted(x for x in p.iterdir() if x.suffix == ".mcap" and x.is_file())
    if not files:
        raise BagError(f"{p}: directory has neither metadata.yaml nor .mcap files")
    return files
