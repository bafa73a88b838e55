"""Read back a smoothed bag that ``pipe-nav smooth`` (or the smoother node) wrote: its
``/pipe_nav/path`` as a Trajectory, its ``/pipe_nav/datum`` and its ``pipe_nav`` metadata.

A cold path (one Path message), so it uses the declared dependencies' own readers: ``mcap``
for the records and rosbags' Jazzy type store for CDR. The Path carries no odometer chainage:
the trajectory's ``distance`` is the arc length of its poses from the first, in m.

:func:`read_smoothed_run` also reads the bag's MCAP attachments that ``pipe-nav smooth`` writes
(:func:`smoothed_attachments`): ``centreline.csv`` (the centreline CSV of INTERFACES.md, with
distance_m and the sigmas, which then replaces the Path) and ``welds.csv`` (RUN_welds.csv).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from pipe_nav_core.geo.earth import enu_to_geodetic
from pipe_nav_core.io.topics import OUTPUT_PATH_TOPIC
from pipe_nav_core.types import Datum, Trajectory

if TYPE_CHECKING:
    from pipe_nav_core.products.welds import Weld

DATUM_TOPIC = "/pipe_nav/datum"
WELDS_ATTACHMENT = "welds.csv"
CENTRELINE_ATTACHMENT = "centreline.csv"
CSV_MEDIA_TYPE = "text/csv"


@dataclass
class SmoothedRun:
    """A smoothed run read back: trajectory (from ``centreline.csv`` with distance_m and
    sigma_enu when the bag has it, else the Path with arc-length distance), datum, the
    ``pipe_nav`` metadata, the welds (``welds.csv``; [] when none) and ``attachments``: the
    names of the attachments found."""

    trajectory: Trajectory
    datum: Datum
    metadata: dict[str, str]
    welds: list[Weld] = field(default_factory=list)
    attachments: list[str] = field(default_factory=list)


def smoothed_attachments(
    centreline: Trajectory, datum: Datum, welds: Sequence[Weld] | None, text: str | None = None
) -> list[tuple[str, str, bytes]]:
    """The attachments of a smoothed bag: ``centreline.csv`` (the centreline CSV text;
    ``text``: its body, when made already) and, when ``welds`` is not None, ``welds.csv`` (the
    RUN_welds.csv text)."""
    from pipe_nav_core.io.centreline import CENTRELINE_HEADER, centreline_text
    from pipe_nav_core.io.welds_csv import welds_text

    body = centreline_text(centreline, datum) if text is None else text
    out = [(CENTRELINE_ATTACHMENT, CSV_MEDIA_TYPE, (CENTRELINE_HEADER + "\n" + body).encode())]
    if welds is not None:
        out.append((WELDS_ATTACHMENT, CSV_MEDIA_TYPE, welds_text(welds).encode()))
    return out


def read_smoothed_run(path: str | os.PathLike[str]) -> SmoothedRun:
    """The smoothed bag with its attachments (module doc); ValueError naming the file (and the
    attachment) when it is not a smoothed bag or an attachment is malformed."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from pipe_nav_core.io.centreline import read_centreline_csv
    from pipe_nav_core.io.welds_csv import parse_welds_text

    p = os.fspath(path)
    traj, datum, metadata = read_smoothed_bag(p)
    found: dict[str, bytes] = {}
    try:
        with open(p, "rb") as f:
            for att in make_reader(f).iter_attachments():
                found[att.name] = bytes(att.data)
    except (McapError, ValueError, KeyError, EOFError) as exc:
        raise ValueError(f"{p}: unreadable attachments ({exc})") from None
    welds = []
    if WELDS_ATTACHMENT in found:
        welds = parse_welds_text(found[WELDS_ATTACHMENT].decode("utf-8"),
                                 f"{p}:{WELDS_ATTACHMENT}")  # fmt: skip
    if CENTRELINE_ATTACHMENT in found:
        with tempfile.TemporaryDirectory() as tmp:
            name = os.path.join(tmp, CENTRELINE_ATTACHMENT)
            with open(name, "wb") as f:
                f.write(found[CENTRELINE_ATTACHMENT])
            try:
                traj, _ = read_centreline_csv(name)
            except ValueError as exc:
                raise ValueError(f"{p}: {str(exc).replace(name, CENTRELINE_ATTACHMENT)}") from None
    return SmoothedRun(traj, datum, metadata, welds, sorted(found))


def read_smoothed_bag(path: str | os.PathLike[str]) -> tuple[Trajectory, Datum, dict[str, str]]:
    """(trajectory, datum, metadata) of a smoothed MCAP bag; ValueError naming the file when
    it is not one (unreadable, no path or no datum)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    p = os.fspath(path)
    store = get_typestore(Stores.ROS2_JAZZY)
    path_msg = datum_msg = None
    metadata: dict[str, str] = {}
    try:
        with open(p, "rb") as f:
            reader = make_reader(f)
            for _schema, channel, message in reader.iter_messages(
                topics=[OUTPUT_PATH_TOPIC, DATUM_TOPIC]
            ):
                if channel.topic == OUTPUT_PATH_TOPIC:
                    path_msg = store.deserialize_cdr(message.data, "nav_msgs/msg/Path")
                else:
                    datum_msg = store.deserialize_cdr(message.data, "sensor_msgs/msg/NavSatFix")
            for record in reader.iter_metadata():
                if record.name == "pipe_nav":
                    metadata = dict(record.metadata)
    except OSError as exc:
        raise ValueError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except (McapError, ValueError, KeyError, EOFError) as exc:
        raise ValueError(f"{p}: not a readable MCAP bag ({exc})") from None
    if path_msg is None or not path_msg.poses:
        raise ValueError(f"{p}: no {OUTPUT_PATH_TOPIC} in it: not a smoothed bag")
    if datum_msg is None:
        raise ValueError(f"{p}: no {DATUM_TOPIC} in it: not a smoothed bag")
    datum = Datum(np.radians(datum_msg.latitude), np.radians(datum_msg.longitude),
                  float(datum_msg.altitude))  # fmt: skip
    poses = path_msg.poses
    t = np.array([ps.header.stamp.sec + 1e-9 * ps.header.stamp.nanosec for ps in poses])
    enu = np.array([[ps.pose.position.x, ps.pose.position.y, ps.pose.position.z] for ps in poses])
    quat = np.array([[ps.pose.orientation.x, ps.pose.orientation.y, ps.pose.orientation.z,
                      ps.pose.orientation.w] for ps in poses])  # fmt: skip
    lat, lon, h = enu_to_geodetic(enu, datum.lat, datum.lon, datum.alt)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(enu, axis=0), axis=1))])
    dt = np.gradient(t) if len(t) > 1 else np.ones(1)
    vel = np.gradient(enu, axis=0) / np.where(dt > 0, dt, 1.0)[:, None] if len(t) > 1 else 0 * enu
    traj = Trajectory(t=t, lat=np.asarray(lat), lon=np.asarray(lon), h=np.asarray(h), vel_n=vel,
                      quat_nb=quat, distance=arc)  # fmt: skip
    return traj, datum, metadata
