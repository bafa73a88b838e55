"""Writing ROS 2 bags: single ``.mcap`` files as rosbag2's MCAP storage writes them.

Profile ``ros2``; one Schema per message type with encoding ``ros2msg`` and the full message
definition text (dependencies after ``====`` / ``MSG: pkg/Type`` lines); one Channel per topic
with ``cdr`` encoding and metadata ``offered_qos_profiles`` (rosbag2 metadata version 9 YAML, the
QoS our nodes publish the topic with: :data:`TOPIC_QOS`) and ``topic_type_hash`` (RIHS01);
log_time = publish_time = header stamp (ns); zstd-compressed chunks with message indexes; the
rosbag2 bag metadata (version 9, ROS distro ``jazzy``, topics with their QoS and counts) in a
Metadata record named ``rosbag2`` (key ``serialized_metadata``), which is where rosbag2's MCAP
storage reads the distro and the metadata version from (``ros2 bag info``); a full summary. The
sensor topics are serialized with numpy (:mod:`.cdr`), so a 1.5-million-message bag is written
in seconds. Files are written atomically (temporary file + rename).

About 480 lines, one module on purpose: the sensor bag and the smoothed bag are written by one
builder (schemas, channels with their QoS, streams, the rosbag2 record) and share its message
encoders.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from functools import cache
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core import __version__
from pipe_nav_core.errors import BagError
from pipe_nav_core.geo.attitude import dcm_from_quat
from pipe_nav_core.io import cdr
from pipe_nav_core.io.atomic import atomic_write, ensure_not_input
from pipe_nav_core.io.centreline import require_finite
from pipe_nav_core.io.mcapwrite import DEFAULT_CHUNK_SIZE, McapWriter, Stream, message_records
from pipe_nav_core.io.msgdefs import DEFINITIONS, HASHES
from pipe_nav_core.io.rosbag2_metadata import (
    ROSBAG2_METADATA_NAME,
    TOPIC_QOS,
    rosbag2_metadata,
    yaml_text,
)
from pipe_nav_core.io.rosmsg import (
    BASE_FRAME,
    COVARIANCE_TYPE_DIAGONAL_KNOWN,
    COVARIANCE_TYPE_UNKNOWN,
    MAP_FRAME,
    ODOM_FRAME,
    SERVICE_GPS,
    STATUS_FIX,
    body_rates_from_quats,
    enu_of,
    jazzy_typestore,
)
from pipe_nav_core.io.stamps import NS_PER_S, sec_to_ns
from pipe_nav_core.io.topics import (
    DEFAULT_TOPICS,
    IMU_TYPE,
    MAG_TYPE,
    NAVSATFIX_TYPE,
    ODOMETRY_TYPE,
    OUTPUT_BENDS_TOPIC,
    OUTPUT_DATUM_TOPIC,
    OUTPUT_ODOMETRY_TOPIC,
    OUTPUT_PATH_TOPIC,
    PATH_TYPE,
    POSE_ARRAY_TYPE,
    TopicNames,
)
from pipe_nav_core.types import Datum, Marker, SensorLog, Trajectory

if TYPE_CHECKING:
    from pipe_nav_core.products.bends import PipeBend

_INT32_MAX_S = 2**31 - 1
RUN_METADATA_NAME = "pipe_nav"  # MCAP Metadata record of what a smoothed run says of itself


@cache
def message_definition(typename: str) -> str:
    """Full ros2msg definition text of a type (with its dependencies), as Jazzy's: stored for
    the types PipeNav writes (io/msgdefs.py), else from rosbags' Jazzy typestore."""
    if typename in DEFINITIONS:
        return DEFINITIONS[typename]
    return jazzy_typestore().generate_msgdef(typename, ros_version=2)[0]


@cache
def type_hash(typename: str) -> str:
    """RIHS01 type description hash (as ROS 2 Jazzy records it), or '' if unavailable."""
    if typename in HASHES:
        return HASHES[typename]
    try:
        return jazzy_typestore().hash_rihs01(typename)
    except Exception:  # pragma: no cover - depends on rosbags version
        return ""


class _BagBuilder:
    """Collects topics (one schema per type) and streams, then writes the MCAP file."""

    def __init__(self) -> None:
        self.schema_ids: dict[str, int] = {}
        self.channels: list[tuple[int, int, str, dict[str, str]]] = []
        self.topics: list[tuple[str, str, dict, str]] = []  # name, type, QoS, hash per channel
        self.streams: list[Stream] = []
        self.metadata: dict[str, dict[str, str]] = {}  # more Metadata records, by name
        self.attachments: list[tuple[str, str, bytes]] = []  # (name, media type, data)

    def channel(self, topic: str, typename: str, qos: dict) -> int:
        """A channel offered with the QoS profile ``qos`` (see :data:`TOPIC_QOS`)."""
        sid = self.schema_ids.setdefault(typename, len(self.schema_ids) + 1)
        cid = len(self.channels) + 1
        meta = {"offered_qos_profiles": yaml_text([qos])}
        h = type_hash(typename)
        if h:
            meta["topic_type_hash"] = h
        self.channels.append((cid, sid, topic, meta))
        self.topics.append((topic, typename, qos, h))
        return cid

    def write(self, f, compression: str, chunk_size: int, file_name: str) -> None:
        w = McapWriter(
            f,
            profile="ros2",
            library=f"pipe_nav_core {__version__}",
            compression=compression,
            chunk_size=chunk_size,
        )
        for typename, sid in self.schema_ids.items():
            w.add_schema(sid, typename, "ros2msg", message_definition(typename))
        for cid, sid, topic, meta in self.channels:
            w.add_channel(cid, sid, topic, "cdr", meta)
        w.write_streams(self.streams)
        meta = rosbag2_metadata(
            file_name=file_name,
            topics=[
                (topic, typename, [qos], h, w.channel_counts.get(cid, 0))
                for (cid, _, _, _), (topic, typename, qos, h) in zip(self.channels, self.topics)
            ],
            message_count=w.message_count,
            start_ns=w.start_time or 0,
            end_ns=w.end_time or 0,
        )
        w.add_metadata(ROSBAG2_METADATA_NAME, {"serialized_metadata": yaml_text(meta)})
        for name, values in self.metadata.items():
            w.add_metadata(name, values)
        for name, media_type, data in self.attachments:
            w.add_attachment(name, media_type, data, w.end_time or 0, w.end_time or 0)
        w.finish()


def _check_times(t_ns: NDArray[np.int64], what: str) -> None:
    if len(t_ns) and (t_ns.min() < 0 or t_ns.max() >= (_INT32_MAX_S + 1) * NS_PER_S):
        raise ValueError(f"{what}: stamps must lie in [0, 2**31) s to be written to a bag")


def _fixed_stream(
    cid: int,
    layout: cdr.MessageLayout,
    strings: dict[str, str],
    t_ns: NDArray[np.int64],
    arrays: dict[str, NDArray],
    consts: dict[str, object],
) -> Stream:
    """A stream of fixed-layout messages serialized on demand, slice by slice."""
    dt, _ = cdr.record_dtype(layout, strings, prefix=31)
    width = dt.itemsize

    def enc(a: int, b: int) -> NDArray[np.uint8]:
        ns = t_ns[a:b]
        sec = np.floor_divide(ns, NS_PER_S)
        values: dict[str, object] = dict(consts)
        values["sec"] = sec
        values["nanosec"] = ns - sec * NS_PER_S
        for k, v in arrays.items():
            values[k] = v[a:b]
        rec = cdr.encode_batch(layout, b - a, values, strings, prefix=31)
        rows = rec.view(np.uint8).reshape(b - a, width)
        return message_records(rows, cid, ns, seq0=a)

    return Stream.fixed(cid, t_ns, width, enc)


def _sorted(t: NDArray[np.float64], *arrays: NDArray) -> tuple[NDArray, ...]:
    t = np.asarray(t, dtype=np.float64)
    if len(t) > 1 and np.any(np.diff(t) < 0):
        order = np.argsort(t, kind="stable")
        return (t[order],) + tuple(np.asarray(a)[order] for a in arrays)
    return (t,) + tuple(np.asarray(a) for a in arrays)


def _cov_diag(var: float | Sequence[float] | None) -> NDArray[np.float64]:
    if var is None:
        return np.zeros(9)
    return np.diag(np.broadcast_to(np.asarray(var, dtype=np.float64), (3,))).reshape(9)


def write_sensor_bag(
    path: str | os.PathLike[str],
    log: SensorLog,
    *,
    imu_frame: str = "imu_link",
    topics: TopicNames = DEFAULT_TOPICS,
    gyro_var: float | Sequence[float] | None = None,
    accel_var: float | Sequence[float] | None = None,
    compression: str = "zstd",
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    inputs: Sequence[str | os.PathLike[str]] = (),
) -> None:
    """Write a SensorLog as a ROS 2 MCAP bag with the input topics of INTERFACES.md.

    /imu/data (sensor_msgs/Imu, frame ``imu_frame``; gyro rad/s, specific force m/s^2; no
    orientation: identity quaternion with orientation_covariance[0] = -1; diagonal noise
    variances gyro_var (rad/s)^2 and accel_var (m/s^2)^2 or zeros), /odom/wheel
    (nav_msgs/Odometry, frame odom, child base_link, position.x = distance m, linear.x = speed
    m/s), /imu/mag (sensor_msgs/MagneticField, tesla, frame ``imu_frame``) and /markers
    (sensor_msgs/NavSatFix per marker, frame_id = name, degrees, ENU diagonal covariance).
    Topics with no samples are not written (no channel). Times are seconds in [0, 2**31);
    log_time = publish_time = header stamp. The topics are offered reliable (:data:`TOPIC_QOS`;
    /markers latched, as the odometer driver publishes them). ``inputs``: paths this must not
    overwrite.
    """
    b = _BagBuilder()
    imu_t, gyro, accel = _sorted(log.imu.t, log.imu.gyro, log.imu.accel)
    odo_t, dist, speed = _sorted(log.odometer.t, log.odometer.distance, log.odometer.speed)
    mag_t, field = _sorted(log.mag.t, log.mag.field)
    ocov = np.zeros(9)
    ocov[0] = -1.0
    if len(imu_t):
        ns = sec_to_ns(imu_t)
        _check_times(ns, topics.imu)
        cid = b.channel(topics.imu, IMU_TYPE, TOPIC_QOS["imu"])
        b.streams.append(
            _fixed_stream(
                cid,
                cdr.IMU,
                {"frame_id": imu_frame},
                ns,
                {
                    "angular_velocity": gyro.reshape(-1, 3),
                    "linear_acceleration": accel.reshape(-1, 3),
                },
                {
                    "orientation": np.array([0.0, 0.0, 0.0, 1.0]),
                    "orientation_covariance": ocov,
                    "angular_velocity_covariance": _cov_diag(gyro_var),
                    "linear_acceleration_covariance": _cov_diag(accel_var),
                },
            )
        )
    if len(odo_t):
        ns = sec_to_ns(odo_t)
        _check_times(ns, topics.odometer)
        cid = b.channel(topics.odometer, ODOMETRY_TYPE, TOPIC_QOS["odometer"])
        n = len(odo_t)
        pos = np.zeros((n, 3))
        pos[:, 0] = dist
        lin = np.zeros((n, 3))
        lin[:, 0] = speed
        b.streams.append(
            _fixed_stream(
                cid,
                cdr.ODOMETRY,
                {"frame_id": ODOM_FRAME, "child_frame_id": BASE_FRAME},
                ns,
                {"position": pos, "linear": lin},
                {"orientation": np.array([0.0, 0.0, 0.0, 1.0])},
            )
        )
    if len(mag_t):
        ns = sec_to_ns(mag_t)
        _check_times(ns, topics.mag)
        cid = b.channel(topics.mag, MAG_TYPE, TOPIC_QOS["mag"])
        b.streams.append(
            _fixed_stream(
                cid,
                cdr.MAGNETIC_FIELD,
                {"frame_id": imu_frame},
                ns,
                {"magnetic_field": field.reshape(-1, 3)},
                {},
            )
        )
    if log.markers:
        _marker_stream(b, topics.markers, log.markers)
    _write(b, path, compression, chunk_size, inputs)


def _navsatfix(
    ns: int,
    frame_id: str,
    lat: float,
    lon: float,
    alt: float,
    cov: NDArray[np.float64],
    cov_type: int,
) -> bytes:
    """A sensor_msgs/NavSatFix (status fix, GPS service) stamped ``ns`` (ns): lat, lon rad
    (written in degrees), alt m ellipsoidal, position covariance (9,) m^2 ENU of ``cov_type``."""
    sec, nsec = divmod(int(ns), NS_PER_S)
    return cdr.encode_one(
        cdr.NAVSATFIX,
        {
            "sec": sec,
            "nanosec": nsec,
            "status": STATUS_FIX,
            "service": SERVICE_GPS,
            "latitude": math.degrees(lat),
            "longitude": math.degrees(lon),
            "altitude": float(alt),
            "position_covariance": cov,
            "position_covariance_type": cov_type,
        },
        {"frame_id": frame_id},
    )


def _marker_stream(b: _BagBuilder, topic: str, markers: Sequence[Marker]) -> None:
    """The marker passages as NavSatFix (rosmsg.marker_to_msg's message: frame_id the name,
    diagonal ENU covariance of the survey sigmas)."""
    ms = sorted(markers, key=lambda m: m.t)
    ns = sec_to_ns(np.array([m.t for m in ms], dtype=np.float64))
    _check_times(ns, topic)
    payloads = [
        _navsatfix(int(k), m.name, m.lat, m.lon, m.alt,
                   np.diag(np.asarray(m.sigma_enu, dtype=np.float64).reshape(3) ** 2).reshape(9),
                   COVARIANCE_TYPE_DIAGONAL_KNOWN)
        for k, m in zip(ns, ms, strict=True)
    ]  # fmt: skip
    cid = b.channel(topic, NAVSATFIX_TYPE, TOPIC_QOS["markers"])
    b.streams.append(Stream.variable(cid, ns.tolist(), payloads))


def _write(
    b: _BagBuilder,
    path: str | os.PathLike[str],
    compression: str,
    chunk_size: int,
    inputs: Sequence[str | os.PathLike[str]],
    file_name: str | None = None,
) -> None:
    ensure_not_input(path, inputs)
    try:
        with atomic_write(path, "wb") as f:
            b.write(f, compression, chunk_size, file_name or os.path.basename(os.fspath(path)))
    except OSError as exc:
        raise BagError(f"{os.fspath(path)}: cannot write ({exc.strerror or exc})") from exc


def _pose_covariances(traj: Trajectory) -> NDArray[np.float64]:
    """(N, 36) pose covariance: the full cov_pose when the trajectory has it, else position from
    sigma_enu and rotation (about E, N, U = map x, y, z) from sigma_att; zeros where unknown."""
    n = len(traj.t)
    if traj.cov_pose is not None:
        return np.asarray(traj.cov_pose, dtype=np.float64).reshape(n, 36)
    cov = np.zeros((n, 6, 6))
    idx = np.arange(3)
    if traj.sigma_enu is not None:
        cov[:, idx, idx] = np.asarray(traj.sigma_enu, dtype=np.float64).reshape(n, 3) ** 2
    if traj.sigma_att is not None:
        cov[:, idx + 3, idx + 3] = np.asarray(traj.sigma_att, dtype=np.float64).reshape(n, 3) ** 2
    return cov.reshape(n, 36)


def write_output_bag(
    bag_path: str | os.PathLike[str],
    /,
    *,
    path: Trajectory | None,
    datum: Datum,
    odometry: Trajectory | None = None,
    stamp: float | None = None,
    compression: str = "zstd",
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    inputs: Sequence[str | os.PathLike[str]] = (),
    file_name: str | None = None,
    run_metadata: Mapping[str, str] | None = None,
    bends: Sequence[PipeBend] = (),
    attachments: Sequence[tuple[str, str, bytes]] = (),
) -> None:
    """Write the estimator's results as a ROS 2 MCAP bag (INTERFACES.md, output topics).

    /pipe_nav/path: one nav_msgs/Path (frame map; one PoseStamped per sample of ``path``,
    position ENU m about the datum, orientation q_nb), stamped ``stamp`` (default: the last
    sample time); not written when ``path`` is None (replay). /pipe_nav/datum: one
    sensor_msgs/NavSatFix (frame map) stamped ``stamp`` (default: the first sample time).
    /pipe_nav/bends: one geometry_msgs/PoseArray (frame map) with the same stamp as the path,
    one Pose per bend of ``bends`` (position = apex ENU m about the datum, orientation =
    apex_quat_nb, x along the pipe); written whenever the path is (an empty PoseArray when
    there is no bend), so that readers can rely on it.
    These channels are offered as latched (reliable, transient local, depth 1), as ekf_node and
    smoother_node publish them.
    /pipe_nav/odometry: one nav_msgs/Odometry per sample of ``odometry`` (frame map, child
    base_link; pose covariance from sigma_enu and sigma_att; twist = body-frame velocity and
    attitude-differenced body rate). ``inputs``: paths this must not overwrite (the input bag).
    ``file_name``: the bag's name in its rosbag2 metadata when it is written under another
    (staged) name. ``run_metadata``: what the run records of itself (quality verdict, IMU
    model...), written as an MCAP Metadata record named ``pipe_nav``. ``attachments``: (name,
    media type, data) of files stored in the bag as MCAP Attachment records (the smoothed run's
    ``welds.csv`` and ``centreline.csv``, io/smoothed_bag.py). The first argument is
    positional-only because ``path`` names the trajectory.
    """
    for traj, what in ((path, "path"), (odometry, "odometry")):
        if traj is not None:
            require_finite(traj, f"{os.fspath(bag_path)}: the {what}")
    b = _BagBuilder()
    times = [np.zeros(0)]
    if path is not None:
        times.append(np.asarray(path.t, dtype=np.float64))
    if odometry is not None:
        times.append(np.asarray(odometry.t, dtype=np.float64))
    all_t = np.concatenate(times)
    t_first = float(all_t.min()) if len(all_t) else 0.0
    t_last = float(all_t.max()) if len(all_t) else 0.0
    if path is not None and len(path.t):
        t_last = float(path.t[-1])
    path_stamp = t_last if stamp is None else float(stamp)
    datum_stamp = t_first if stamp is None else float(stamp)
    path_ns = int(sec_to_ns(path_stamp))
    datum_ns = int(sec_to_ns(datum_stamp))
    _check_times(np.array([path_ns, datum_ns], dtype=np.int64), "output stamp")

    if path is not None:
        cid = b.channel(OUTPUT_PATH_TOPIC, PATH_TYPE, TOPIC_QOS["path"])
        enu = enu_of(datum, path.lat, path.lon, path.h).reshape(-1, 3)
        path_t_ns = sec_to_ns(np.asarray(path.t, dtype=np.float64))
        payload = cdr.encode_path(
            path_ns, path_t_ns, enu, np.asarray(path.quat_nb, dtype=np.float64).reshape(-1, 4)
        )
        b.streams.append(Stream.variable(cid, [path_ns], [payload]))
        apex = np.array([[x.lat, x.lon, x.alt] for x in bends], dtype=np.float64).reshape(-1, 3)
        cid = b.channel(OUTPUT_BENDS_TOPIC, POSE_ARRAY_TYPE, TOPIC_QOS["bends"])
        payload = cdr.encode_pose_array(
            path_ns,
            enu_of(datum, apex[:, 0], apex[:, 1], apex[:, 2]).reshape(-1, 3),
            np.array([x.apex_quat_nb for x in bends], dtype=np.float64).reshape(-1, 4),
            MAP_FRAME,
        )
        b.streams.append(Stream.variable(cid, [path_ns], [payload]))

    cid = b.channel(OUTPUT_DATUM_TOPIC, NAVSATFIX_TYPE, TOPIC_QOS["datum"])
    payload = _navsatfix(datum_ns, MAP_FRAME, datum.lat, datum.lon, datum.alt, np.zeros(9),
                         COVARIANCE_TYPE_UNKNOWN)  # fmt: skip
    b.streams.append(Stream.variable(cid, [datum_ns], [payload]))

    if odometry is not None and len(odometry.t):
        o_t, order = np.asarray(odometry.t, dtype=np.float64), None
        if len(o_t) > 1 and np.any(np.diff(o_t) < 0):
            order = np.argsort(o_t, kind="stable")
        sel = (lambda a: np.asarray(a)[order]) if order is not None else np.asarray
        o_t = sel(o_t)
        q = sel(np.asarray(odometry.quat_nb, dtype=np.float64).reshape(-1, 4))
        ns = sec_to_ns(o_t)
        _check_times(ns, OUTPUT_ODOMETRY_TOPIC)
        pos = enu_of(datum, sel(odometry.lat), sel(odometry.lon), sel(odometry.h)).reshape(-1, 3)
        vel_n = sel(np.asarray(odometry.vel_n, dtype=np.float64).reshape(-1, 3))
        v_b = np.einsum("nji,nj->ni", dcm_from_quat(q), vel_n)
        omega = body_rates_from_quats(o_t, q)
        cov = _pose_covariances(odometry)
        if order is not None:
            cov = cov[order]
        cid = b.channel(OUTPUT_ODOMETRY_TOPIC, ODOMETRY_TYPE, TOPIC_QOS["odometry"])
        b.streams.append(
            _fixed_stream(
                cid,
                cdr.ODOMETRY,
                {"frame_id": MAP_FRAME, "child_frame_id": BASE_FRAME},
                ns,
                {
                    "position": pos,
                    "orientation": q,
                    "pose_covariance": cov,
                    "linear": v_b,
                    "angular": omega,
                },
                {},
            )
        )
    if run_metadata:
        b.metadata[RUN_METADATA_NAME] = dict(run_metadata)
    b.attachments = [(str(n), str(m), bytes(d)) for n, m, d in attachments]
    _write(b, bag_path, compression, chunk_size, inputs, file_name)
