"""A bag written again by rosbags (a library no one here wrote) in the other forms rosbag2
writes: sqlite3 or MCAP storage, zstd compression of whole files or of each message. The
speed bench reads and smooths them beside the MCAP forms; the tests check that each reads as
the bag it was made from.
"""

from __future__ import annotations

import os
from pathlib import Path

STORAGES = ("mcap", "sqlite3")
COMPRESSIONS = ("", "file", "message")  # rosbag2's compression modes, "" for none


def rewrite(
    src: str | os.PathLike[str], out: str | os.PathLike[str], storage: str, compression: str = ""
) -> Path:
    """The messages of the MCAP file ``src`` as they are (log times, payloads, file order)
    written by rosbags as the rosbag2 directory ``out`` (made; it must not exist) of that
    ``storage`` (STORAGES) and ``compression`` (COMPRESSIONS, zstd)."""
    from mcap.reader import make_reader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.typesys import Stores, get_typestore

    if storage not in STORAGES or compression not in COMPRESSIONS:
        raise ValueError(f"no rosbag2 form {storage!r} with compression {compression!r}")
    store = get_typestore(Stores.ROS2_JAZZY)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    w = Writer(Path(out), version=9, storage_plugin=plugin)
    if compression:
        mode = CompressionMode.FILE if compression == "file" else CompressionMode.MESSAGE
        w.set_compression(mode, CompressionFormat.ZSTD)
    w.open()
    try:
        conns = {}
        with open(src, "rb") as f:
            for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
                if channel.id not in conns:
                    conns[channel.id] = w.add_connection(channel.topic, schema.name,
                                                         typestore=store)  # fmt: skip
                w.write(conns[channel.id], message.log_time, message.data)
    finally:
        w.close()
    return Path(out)
