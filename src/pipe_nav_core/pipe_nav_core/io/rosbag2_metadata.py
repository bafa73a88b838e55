"""rosbag2's bag metadata and QoS records, as ROS 2 Jazzy's MCAP storage writes them: the
offered QoS profile of each topic (channel metadata ``offered_qos_profiles``), the bag metadata
(version 9: topics, counts, times; in the ``rosbag2`` Metadata record and in a directory's
``metadata.yaml``) and the block YAML they are written in, laid out as rosbag2 (yaml-cpp)
writes it so that the text is the same as a bag recorded by ``ros2 bag record``. Times are
integer nanoseconds since 1970.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from typing import Any

from pipe_nav_core.errors import BagError
from pipe_nav_core.io.atomic import atomic_write

ROS_DISTRO = "jazzy"  # what the bags are written for (rosbag2 metadata ros_distro)


ROSBAG2_METADATA_VERSION = 9  # rosbag2 bag metadata version of ROS 2 Jazzy


ROSBAG2_METADATA_NAME = "rosbag2"  # name of the MCAP Metadata record rosbag2 reads


_INFINITE = {"sec": 9223372036, "nsec": 854775807}  # RMW_DURATION_INFINITE as rosbag2 writes it


def qos_profile(*, reliable: bool = True, transient_local: bool = False, depth: int = 10) -> dict:
    """One offered QoS profile as rosbag2 (metadata version 9, ROS 2 Jazzy) records it: history
    keep_last with ``depth`` messages, reliability ``reliable`` or ``best_effort``, durability
    ``transient_local`` (latched) or ``volatile``, liveliness automatic, infinite durations."""
    return {
        "history": "keep_last",
        "depth": int(depth),
        "reliability": "reliable" if reliable else "best_effort",
        "durability": "transient_local" if transient_local else "volatile",
        "deadline": dict(_INFINITE),
        "lifespan": dict(_INFINITE),
        "liveliness": "automatic",
        "liveliness_lease_duration": dict(_INFINITE),
        "avoid_ros_namespace_conventions": False,
    }


def qos_profiles_yaml(
    *, transient_local: bool = False, reliable: bool = True, depth: int = 10
) -> str:
    """The channel metadata ``offered_qos_profiles`` string (a YAML list of one
    :func:`qos_profile`), as rosbag2's MCAP storage of ROS 2 Jazzy writes it."""
    return yaml_text([qos_profile(reliable=reliable, transient_local=transient_local, depth=depth)])


# The offered QoS recorded per topic (keys: the topics' roles), which ``ros2 bag play`` offers
# again: what the pipe_nav_ros nodes publish with (src/pipe_nav_ros/README.md), except that the
# sensor data are offered reliable (the drivers publish them best effort, depth 50): a reliable
# offer matches best-effort and reliable subscribers alike, so a replay reaches every node. The
# markers are latched as the odometer driver publishes them (depth 1000); ekf_node's
# /pipe_nav/odometry is reliable (depth 50); the datum, the smoothed path and the bend apexes
# are latched (reliable, transient local, depth 1).
TOPIC_QOS: dict[str, dict] = {
    "imu": qos_profile(depth=50),
    "odometer": qos_profile(depth=50),
    "mag": qos_profile(depth=50),
    "markers": qos_profile(transient_local=True, depth=1000),
    "odometry": qos_profile(depth=50),
    "datum": qos_profile(transient_local=True, depth=1),
    "path": qos_profile(transient_local=True, depth=1),
    "bends": qos_profile(transient_local=True, depth=1),
}


_PLAIN = re.compile(r"[A-Za-z_/][A-Za-z0-9_/.\-]*")


_YAML_WORDS = {"true", "false", "yes", "no", "on", "off", "null", "y", "n"}


def _yaml_scalar(value: Any) -> str:
    if value is None:
        return "~"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return ".nan" if math.isnan(value) else (".inf" if value > 0 else "-.inf")
        mantissa, e, exponent = repr(value).partition("e")
        if e and "." not in mantissa:  # 1e-06 -> 1.0e-06, a float in YAML 1.1 and 1.2
            mantissa += ".0"
        return mantissa + e + exponent
    if isinstance(value, Mapping):
        return "{}"  # an empty mapping (non-empty ones are blocks)
    if isinstance(value, (list, tuple)):
        return "[]"
    text = str(value)
    if _PLAIN.fullmatch(text) and text.lower() not in _YAML_WORDS:
        return text
    return json.dumps(text)  # a JSON string is a YAML double-quoted scalar


def _yaml_lines(value: Any, indent: int) -> list[str]:
    pad = " " * indent
    if isinstance(value, Mapping):
        lines = []
        for key, v in value.items():
            if isinstance(v, Mapping) and v:
                lines += [f"{pad}{key}:"] + _yaml_lines(v, indent + 2)
            elif isinstance(v, (list, tuple)):
                lines += [f"{pad}{key}:"] + (_yaml_lines(v, indent + 2) if v else [pad + "  []"])
            else:
                lines.append(f"{pad}{key}: {_yaml_scalar(v)}")
        return lines
    if isinstance(value, (list, tuple)):
        lines = []
        for item in value:
            if isinstance(item, (Mapping, list, tuple)) and item:
                sub = _yaml_lines(item, indent + 2)
                lines += [pad + "- " + sub[0][indent + 2 :]] + sub[1:]
            else:
                lines.append(f"{pad}- {_yaml_scalar(item)}")
        return lines
    return [pad + _yaml_scalar(value)]


def yaml_text(value: Any) -> str:
    """Block-style YAML of nested dicts (plain keys), lists and scalars (str, int, float, bool,
    None), laid out as rosbag2 (yaml-cpp) writes its metadata (no trailing newline)."""
    return "\n".join(_yaml_lines(value, 0))


def rosbag2_metadata(
    *,
    file_name: str,
    topics: Sequence[tuple[str, str, Sequence[Mapping[str, Any]], str, int]],
    message_count: int,
    start_ns: int,
    end_ns: int,
) -> dict[str, Any]:
    """rosbag2 bag metadata (version 9, ROS distro jazzy) of a single-file MCAP bag.

    topics: (name, type, offered QoS profiles, RIHS01 type hash or '', message count) per
    channel; start_ns, end_ns: first and last log time (ns since 1970). The ``rosbag2``
    Metadata record holds this (``serialized_metadata``); metadata.yaml holds it under
    ``rosbag2_bagfile_information``.
    """
    start = int(start_ns) if message_count else 0
    duration = max(0, int(end_ns) - int(start_ns)) if message_count else 0
    return {
        "version": ROSBAG2_METADATA_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": int(message_count),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": name,
                    "type": typename,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": [dict(q) for q in qos],
                    "type_description_hash": type_hash_,
                },
                "message_count": int(count),
            }
            for name, typename, qos, type_hash_, count in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [file_name],
        "files": [
            {
                "path": file_name,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": duration},
                "message_count": int(message_count),
            }
        ],
        "custom_data": None,
        "ros_distro": ROS_DISTRO,
    }


# rosbag2 metadata version 8 wrote the QoS policies as the rmw enum values
_QOS_V8_NAMES = {
    "history": {0: "system_default", 1: "keep_last", 2: "keep_all", 3: "unknown"},
    "reliability": {
        0: "system_default",
        1: "reliable",
        2: "best_effort",
        3: "unknown",
        4: "best_available",
    },
    "durability": {
        0: "system_default",
        1: "transient_local",
        2: "volatile",
        3: "unknown",
        4: "best_available",
    },
    "liveliness": {
        0: "system_default",
        1: "automatic",
        2: "manual_by_node",
        3: "manual_by_topic",
        4: "unknown",
        5: "best_available",
    },
}


def qos_profiles_from_text(text: str) -> list[dict[str, Any]]:
    """A channel's ``offered_qos_profiles`` string (rosbag2 metadata version 8 with enum numbers,
    or 9 with names) as a list of version-9 profiles; [] when empty or unreadable."""
    from ruamel.yaml import YAML, YAMLError

    try:
        data = YAML(typ="safe", pure=True).load(text) if text.strip() else None
    except YAMLError:
        return []
    if not isinstance(data, list):
        return []
    out = []
    for item in data:
        if not isinstance(item, dict):
            continue
        profile = dict(item)
        for key, names in _QOS_V8_NAMES.items():
            value = profile.get(key)
            if isinstance(value, int) and not isinstance(value, bool):
                profile[key] = names.get(value, "unknown")
        out.append(profile)
    return out


def write_rosbag2_metadata(bag_file: str | os.PathLike[str]) -> str:
    """Write a rosbag2 ``metadata.yaml`` (version 9, ROS distro jazzy) beside a single-file MCAP
    bag, so that its directory is also a rosbag2 bag for tools that insist on one (older
    rosbags, older ``ros2 bag``). Topics, counts and times come from the MCAP summary; the QoS
    from each channel's ``offered_qos_profiles`` (version 8 enum numbers are written as names).
    Returns the metadata path."""
    from pipe_nav_core.io.mcapread import read_summary

    f = os.fspath(bag_file)
    summ = read_summary(f)
    if summ is None or summ.message_count is None:
        raise BagError(f"{f}: no MCAP summary to build metadata.yaml from")
    counts = summ.channel_message_counts or {}
    topics = []
    for cid, ch in sorted(summ.channels.items()):
        sch = summ.schemas.get(ch.schema_id)
        topics.append(
            (
                ch.topic,
                sch.name if sch else "",
                qos_profiles_from_text(ch.metadata.get("offered_qos_profiles", "")),
                ch.metadata.get("topic_type_hash", ""),
                counts.get(cid, 0),
            )
        )
    meta = rosbag2_metadata(
        file_name=os.path.basename(f),
        topics=topics,
        message_count=summ.message_count,
        start_ns=int(summ.message_start_time or 0),
        end_ns=int(summ.message_end_time or 0),
    )
    out = os.path.join(os.path.dirname(os.path.abspath(f)), "metadata.yaml")
    with atomic_write(out, "w") as fh:
        fh.write(yaml_text({"rosbag2_bagfile_information": meta}) + "\n")
    return out
