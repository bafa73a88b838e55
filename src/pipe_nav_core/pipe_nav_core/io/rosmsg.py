"""Conversion between ROS 2 messages and core values, shared by the ROS nodes and the core.

Every builder takes a :class:`MsgTypes` (the message classes to instantiate) and passes every
field as a keyword, and every reader only uses attribute access, so the same functions work
with rosbags' typestore classes (:func:`rosbags_types`, used for bags and tests) and with the
real rclpy classes (the ROS package builds its own MsgTypes from sensor_msgs.msg etc.).
Fixed-size float arrays (covariances) are passed as float64 numpy arrays of the right length,
which both rosbags and rclpy accept.

Frames and units follow INTERFACES.md: SI units; quaternions scalar-last [x, y, z, w] rotating
base_link into map (ENU); NavSatFix latitude/longitude in degrees (ROS convention), altitude
ellipsoidal metres; inside the core latitude/longitude are radians.

About 520 lines, one module on purpose: two dozen converters, most in matching pairs
(``imu_to_msg`` / ``imu_from_msg``), public as one module (``pipe_nav_core.rosmsg``) so that a
ROS integrator finds both directions of every message in one place.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.geo.attitude import dcm_from_quat, quat_conj, quat_mul, rotvec_from_quat
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.io.stamps import NS_PER_S, ns_to_sec_scalar, sec_to_ns_scalar
from pipe_nav_core.types import Datum, Marker, SensorLog, Trajectory

if TYPE_CHECKING:
    from pipe_nav_core.products.bends import PipeBend

DEFAULT_MARKER_SIGMA_M = 0.05  # used when a NavSatFix carries no usable covariance

COVARIANCE_TYPE_UNKNOWN = 0
COVARIANCE_TYPE_APPROXIMATED = 1
COVARIANCE_TYPE_DIAGONAL_KNOWN = 2
COVARIANCE_TYPE_KNOWN = 3
STATUS_FIX = 0
SERVICE_GPS = 1

MAP_FRAME = "map"
BASE_FRAME = "base_link"
ODOM_FRAME = "odom"
IMU_FRAME = "imu_link"


@dataclass(frozen=True)
class MsgTypes:
    """Message classes used by the builders. ``byte_as_bytes``: how ``byte`` fields
    (DiagnosticStatus.level) are set -- rclpy wants ``bytes`` of length 1, rosbags an int;
    None detects it (rosbags classes have ``__msgtype__``)."""

    Time: Any
    Header: Any
    Imu: Any
    Odometry: Any
    MagneticField: Any
    NavSatFix: Any
    NavSatStatus: Any
    Path: Any
    PoseStamped: Any
    PoseArray: Any
    Pose: Any
    PoseWithCovariance: Any
    Twist: Any
    TwistWithCovariance: Any
    Point: Any
    Quaternion: Any
    Vector3: Any
    DiagnosticArray: Any
    DiagnosticStatus: Any
    KeyValue: Any
    byte_as_bytes: bool | None = None

    def _byte(self, v: int) -> Any:
        as_bytes = self.byte_as_bytes
        if as_bytes is None:
            as_bytes = not hasattr(self.DiagnosticStatus, "__msgtype__")
        return bytes([int(v) & 0xFF]) if as_bytes else int(v)


@lru_cache(maxsize=1)
def jazzy_typestore() -> Any:
    """The rosbags typestore for ROS 2 Jazzy (cached)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@lru_cache(maxsize=1)
def rosbags_types() -> MsgTypes:
    """MsgTypes made of the rosbags Jazzy typestore classes."""
    t = jazzy_typestore().types
    return MsgTypes(
        Time=t["builtin_interfaces/msg/Time"],
        Header=t["std_msgs/msg/Header"],
        Imu=t["sensor_msgs/msg/Imu"],
        Odometry=t["nav_msgs/msg/Odometry"],
        MagneticField=t["sensor_msgs/msg/MagneticField"],
        NavSatFix=t["sensor_msgs/msg/NavSatFix"],
        NavSatStatus=t["sensor_msgs/msg/NavSatStatus"],
        Path=t["nav_msgs/msg/Path"],
        PoseStamped=t["geometry_msgs/msg/PoseStamped"],
        PoseArray=t["geometry_msgs/msg/PoseArray"],
        Pose=t["geometry_msgs/msg/Pose"],
        PoseWithCovariance=t["geometry_msgs/msg/PoseWithCovariance"],
        Twist=t["geometry_msgs/msg/Twist"],
        TwistWithCovariance=t["geometry_msgs/msg/TwistWithCovariance"],
        Point=t["geometry_msgs/msg/Point"],
        Quaternion=t["geometry_msgs/msg/Quaternion"],
        Vector3=t["geometry_msgs/msg/Vector3"],
        DiagnosticArray=t["diagnostic_msgs/msg/DiagnosticArray"],
        DiagnosticStatus=t["diagnostic_msgs/msg/DiagnosticStatus"],
        KeyValue=t["diagnostic_msgs/msg/KeyValue"],
        byte_as_bytes=False,
    )


# ----------------------------------------------------------------------------- time


def stamp_to_sec(stamp: Any) -> float:
    """builtin_interfaces/Time -> seconds: integer nanoseconds first, then one correctly rounded
    division (same rule as the bag reader, :func:`.stamps.ns_to_sec`)."""
    return ns_to_sec_scalar(int(stamp.sec) * NS_PER_S + int(stamp.nanosec))


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(types: MsgTypes, ns: int) -> Any:
    """Integer nanoseconds -> builtin_interfaces/Time (negative-safe: nanosec in [0, 1e9))."""
    sec, nsec = divmod(int(ns), NS_PER_S)
    return types.Time(sec=int(sec), nanosec=int(nsec))


def sec_to_stamp(types: MsgTypes, t: float) -> Any:
    """Seconds -> builtin_interfaces/Time, rounded to the nearest nanosecond, negative-safe
    (-1.7 s -> sec=-2, nanosec=300000000)."""
    return ns_to_stamp(types, sec_to_ns_scalar(t))


def _header(types: MsgTypes, t: float, frame_id: str) -> Any:
    return types.Header(stamp=sec_to_stamp(types, t), frame_id=str(frame_id))


def _vec3(types: MsgTypes, v: ArrayLike) -> Any:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    return types.Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2]))


def _point(types: MsgTypes, v: ArrayLike) -> Any:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    return types.Point(x=float(a[0]), y=float(a[1]), z=float(a[2]))


def _quat(types: MsgTypes, q: ArrayLike) -> Any:
    a = np.asarray(q, dtype=np.float64).reshape(4)
    return types.Quaternion(x=float(a[0]), y=float(a[1]), z=float(a[2]), w=float(a[3]))


def _xyz(v: Any) -> NDArray[np.float64]:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def _cov3(var: ArrayLike | None) -> NDArray[np.float64]:
    """float64[9] row-major covariance with ``var`` (scalar, 3-vector or 3x3) or zeros."""
    if var is None:
        return np.zeros(9, dtype=np.float64)
    a = np.asarray(var, dtype=np.float64)
    if a.size == 9:
        return a.reshape(9).copy()
    return np.diag(np.broadcast_to(a, (3,)).astype(np.float64)).reshape(9)


def _cov6(cov: ArrayLike | None) -> NDArray[np.float64]:
    """float64[36] row-major from a 6x6 / 36 array, a 6-vector of variances, or None (zeros)."""
    if cov is None:
        return np.zeros(36, dtype=np.float64)
    a = np.asarray(cov, dtype=np.float64)
    if a.size == 36:
        return a.reshape(36).copy()
    return np.diag(a.reshape(6)).reshape(36)


# ----------------------------------------------------------------------------- input topics


def imu_to_msg(
    types: MsgTypes,
    t: float,
    gyro: ArrayLike,
    accel: ArrayLike,
    frame_id: str = IMU_FRAME,
    gyro_var: ArrayLike | None = None,
    accel_var: ArrayLike | None = None,
) -> Any:
    """sensor_msgs/Imu: gyro rad/s and accel (specific force) m/s^2 in ``frame_id``; no
    orientation (all zero, orientation_covariance[0] = -1); gyro_var/accel_var: per-sample
    noise variances (scalar, 3-vector or 3x3) or None for zeros (unknown). The orientation is
    the ROS 2 default identity quaternion (a valid one for viewers), flagged unused by
    orientation_covariance[0] = -1."""
    ocov = np.zeros(9, dtype=np.float64)
    ocov[0] = -1.0
    return types.Imu(
        header=_header(types, t, frame_id),
        orientation=types.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=ocov,
        angular_velocity=_vec3(types, gyro),
        angular_velocity_covariance=_cov3(gyro_var),
        linear_acceleration=_vec3(types, accel),
        linear_acceleration_covariance=_cov3(accel_var),
    )


def imu_from_msg(msg: Any) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """sensor_msgs/Imu -> (t s, gyro rad/s (3,), accel m/s^2 (3,)) in the message frame."""
    return (
        stamp_to_sec(msg.header.stamp),
        _xyz(msg.angular_velocity),
        _xyz(msg.linear_acceleration),
    )


def wheel_to_msg(types: MsgTypes, t: float, distance: float, speed: float) -> Any:
    """nav_msgs/Odometry of the wheel odometer (frame odom, child base_link): pose.position.x =
    cumulative distance m, twist.linear.x = speed m/s, every other field zero except the
    orientation, which is the ROS 2 default identity quaternion (w = 1)."""
    return types.Odometry(
        header=_header(types, t, ODOM_FRAME),
        child_frame_id=BASE_FRAME,
        pose=types.PoseWithCovariance(
            pose=types.Pose(
                position=types.Point(x=float(distance), y=0.0, z=0.0),
                orientation=types.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            covariance=np.zeros(36, dtype=np.float64),
        ),
        twist=types.TwistWithCovariance(
            twist=types.Twist(
                linear=types.Vector3(x=float(speed), y=0.0, z=0.0),
                angular=types.Vector3(x=0.0, y=0.0, z=0.0),
            ),
            covariance=np.zeros(36, dtype=np.float64),
        ),
    )


def wheel_from_msg(msg: Any) -> tuple[float, float, float]:
    """nav_msgs/Odometry (wheel) -> (t s, distance m, speed m/s)."""
    return (
        stamp_to_sec(msg.header.stamp),
        float(msg.pose.pose.position.x),
        float(msg.twist.twist.linear.x),
    )


def mag_to_msg(types: MsgTypes, t: float, field: ArrayLike, frame_id: str = IMU_FRAME) -> Any:
    """sensor_msgs/MagneticField: field in tesla in ``frame_id``, covariance zero (unknown)."""
    return types.MagneticField(
        header=_header(types, t, frame_id),
        magnetic_field=_vec3(types, field),
        magnetic_field_covariance=np.zeros(9, dtype=np.float64),
    )


def mag_from_msg(msg: Any) -> tuple[float, NDArray[np.float64]]:
    """sensor_msgs/MagneticField -> (t s, field tesla (3,))."""
    return stamp_to_sec(msg.header.stamp), _xyz(msg.magnetic_field)


def marker_to_msg(types: MsgTypes, marker: Marker) -> Any:
    """sensor_msgs/NavSatFix of a marker passage: header.frame_id = name, stamp = passage time,
    lat/lon degrees, altitude ellipsoidal m, diagonal ENU covariance (DIAGONAL_KNOWN)."""
    s = np.asarray(marker.sigma_enu, dtype=np.float64).reshape(3)
    return types.NavSatFix(
        header=_header(types, marker.t, marker.name),
        status=types.NavSatStatus(status=STATUS_FIX, service=SERVICE_GPS),
        latitude=math.degrees(marker.lat),
        longitude=math.degrees(marker.lon),
        altitude=float(marker.alt),
        position_covariance=np.diag(s * s).reshape(9),
        position_covariance_type=COVARIANCE_TYPE_DIAGONAL_KNOWN,
    )


def log_to_messages(
    types: MsgTypes, log: SensorLog, t_end: float = math.inf
) -> list[tuple[float, str, Any]]:
    """(stamp s, role, message) of every sample and marker of a log stamped up to t_end (s), in
    stamp order; roles "imu", "odometer", "mag", "markers" (the input topics'
    INTERFACES.md roles). Vectors stay in the log's frame (imu_link as recorded)."""
    imu, odo, mag = log.imu, log.odometer, log.mag
    out: list[tuple[float, str, Any]] = []
    for i in np.flatnonzero(imu.t <= t_end):
        out.append((imu.t[i], "imu", imu_to_msg(types, imu.t[i], imu.gyro[i], imu.accel[i])))
    for i in np.flatnonzero(odo.t <= t_end):
        out.append(
            (odo.t[i], "odometer", wheel_to_msg(types, odo.t[i], odo.distance[i], odo.speed[i]))
        )
    for i in np.flatnonzero(mag.t <= t_end):
        out.append((mag.t[i], "mag", mag_to_msg(types, mag.t[i], mag.field[i])))
    out += [(m.t, "markers", marker_to_msg(types, m)) for m in log.markers if m.t <= t_end]
    out.sort(key=lambda x: x[0])
    return out


def marker_from_msg(msg: Any) -> Marker:
    """sensor_msgs/NavSatFix -> Marker (name = header.frame_id, lat/lon radians, alt m).

    sigma_enu from the diagonal of position_covariance (ENU, m^2); when the covariance type is
    UNKNOWN or a diagonal entry is not a positive finite number, DEFAULT_MARKER_SIGMA_M (0.05 m)
    is used for that axis.
    """
    cov = np.asarray(msg.position_covariance, dtype=np.float64).reshape(9)
    ctype = int(msg.position_covariance_type)
    sig = []
    for k in (0, 4, 8):
        v = cov[k]
        ok = ctype != COVARIANCE_TYPE_UNKNOWN and math.isfinite(v) and v > 0.0
        sig.append(math.sqrt(v) if ok else DEFAULT_MARKER_SIGMA_M)
    return Marker(
        name=str(msg.header.frame_id),
        t=stamp_to_sec(msg.header.stamp),
        lat=math.radians(float(msg.latitude)),
        lon=math.radians(float(msg.longitude)),
        alt=float(msg.altitude),
        sigma_enu=(sig[0], sig[1], sig[2]),
    )


# ----------------------------------------------------------------------------- outputs


def enu_of(datum: Datum, lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> NDArray[np.float64]:
    """ENU position (m) in ``map`` of geodetic points (rad, rad, m) about the datum."""
    return geodetic_to_enu(lat, lon, h, datum.lat, datum.lon, datum.alt)


def odometry_to_msg(
    types: MsgTypes,
    t: float,
    datum: Datum,
    lat: float,
    lon: float,
    h: float,
    quat_nb: ArrayLike,
    vel_n: ArrayLike,
    omega_b: ArrayLike,
    cov_pose6: ArrayLike | None,
    cov_twist6: ArrayLike | None = None,
) -> Any:
    """nav_msgs/Odometry of the estimate: frame map, child base_link.

    pose.position: ENU (m) of (lat, lon rad, h m) about the datum; orientation: q_nb [x,y,z,w];
    pose.covariance: 6x6 row-major over (x, y, z, rotX, rotY, rotZ) -- a (6, 6)/(36,) array or a
    6-vector of variances; twist.linear: C_bn vel_n (body frame, m/s); twist.angular: omega_b
    (rad/s); twist.covariance likewise (zeros when None).
    """
    q = np.asarray(quat_nb, dtype=np.float64).reshape(4)
    pos = enu_of(datum, lat, lon, h).reshape(3)
    v_b = dcm_from_quat(q).T @ np.asarray(vel_n, dtype=np.float64).reshape(3)
    return types.Odometry(
        header=_header(types, t, MAP_FRAME),
        child_frame_id=BASE_FRAME,
        pose=types.PoseWithCovariance(
            pose=types.Pose(position=_point(types, pos), orientation=_quat(types, q)),
            covariance=_cov6(cov_pose6),
        ),
        twist=types.TwistWithCovariance(
            twist=types.Twist(linear=_vec3(types, v_b), angular=_vec3(types, omega_b)),
            covariance=_cov6(cov_twist6),
        ),
    )


def odometry_from_msg(msg: Any) -> dict[str, Any]:
    """nav_msgs/Odometry -> dict t, position (3,), quat (4,), pose_cov (6, 6), vel_b (3,),
    omega_b (3,), twist_cov (6, 6), frame_id, child_frame_id."""
    p = msg.pose.pose
    return {
        "t": stamp_to_sec(msg.header.stamp),
        "frame_id": str(msg.header.frame_id),
        "child_frame_id": str(msg.child_frame_id),
        "position": _xyz(p.position),
        "quat": np.array(
            [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w], dtype=np.float64
        ),
        "pose_cov": np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6),
        "vel_b": _xyz(msg.twist.twist.linear),
        "omega_b": _xyz(msg.twist.twist.angular),
        "twist_cov": np.asarray(msg.twist.covariance, dtype=np.float64).reshape(6, 6),
    }


def path_to_msg(types: MsgTypes, traj: Trajectory, datum: Datum, t: float | None = None) -> Any:
    """nav_msgs/Path in map: one PoseStamped per trajectory sample (stamp = sample time,
    position = ENU about the datum, orientation = q_nb). Header stamp: t, or the last sample's
    time (0 for an empty trajectory)."""
    enu = enu_of(datum, traj.lat, traj.lon, traj.h).reshape(-1, 3)
    q = np.asarray(traj.quat_nb, dtype=np.float64).reshape(-1, 4)
    times = np.asarray(traj.t, dtype=np.float64)
    if t is None:
        t = float(times[-1]) if len(times) else 0.0
    poses = [
        types.PoseStamped(
            header=_header(types, float(times[i]), MAP_FRAME),
            pose=types.Pose(position=_point(types, enu[i]), orientation=_quat(types, q[i])),
        )
        for i in range(len(times))
    ]
    return types.Path(header=_header(types, t, MAP_FRAME), poses=poses)


def path_from_msg(msg: Any) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """nav_msgs/Path -> (t (N,), enu (N, 3), quat (N, 4))."""
    n = len(msg.poses)
    t = np.empty(n)
    enu = np.empty((n, 3))
    q = np.empty((n, 4))
    for i, ps in enumerate(msg.poses):
        t[i] = stamp_to_sec(ps.header.stamp)
        enu[i] = _xyz(ps.pose.position)
        o = ps.pose.orientation
        q[i] = (o.x, o.y, o.z, o.w)
    return t, enu, q


def bends_to_msg(types: MsgTypes, bends: Sequence[PipeBend], datum: Datum, t: float) -> Any:
    """geometry_msgs/PoseArray of the bend apexes in map, stamped ``t`` (s; the path's stamp):
    one Pose per bend in bend order, position = ENU (m) of the apex (lat, lon, alt) about the
    datum, orientation = apex_quat_nb [x, y, z, w] (x along the pipe, downstream). No bend: an
    empty PoseArray."""
    if bends:
        enu = enu_of(
            datum,
            np.array([b.lat for b in bends], dtype=np.float64),
            np.array([b.lon for b in bends], dtype=np.float64),
            np.array([b.alt for b in bends], dtype=np.float64),
        ).reshape(-1, 3)
    else:
        enu = np.zeros((0, 3))
    poses = [
        types.Pose(position=_point(types, enu[i]), orientation=_quat(types, b.apex_quat_nb))
        for i, b in enumerate(bends)
    ]
    return types.PoseArray(header=_header(types, t, MAP_FRAME), poses=poses)


def pose_array_from_msg(msg: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """geometry_msgs/PoseArray -> (position (N, 3), quat [x, y, z, w] (N, 4))."""
    n = len(msg.poses)
    pos = np.empty((n, 3))
    q = np.empty((n, 4))
    for i, p in enumerate(msg.poses):
        pos[i] = _xyz(p.position)
        o = p.orientation
        q[i] = (o.x, o.y, o.z, o.w)
    return pos, q


def datum_to_msg(types: MsgTypes, datum: Datum, t: float) -> Any:
    """sensor_msgs/NavSatFix of the map origin: frame map, lat/lon degrees, altitude m
    (ellipsoidal), covariance unknown."""
    return types.NavSatFix(
        header=_header(types, t, MAP_FRAME),
        status=types.NavSatStatus(status=STATUS_FIX, service=SERVICE_GPS),
        latitude=math.degrees(datum.lat),
        longitude=math.degrees(datum.lon),
        altitude=float(datum.alt),
        position_covariance=np.zeros(9, dtype=np.float64),
        position_covariance_type=COVARIANCE_TYPE_UNKNOWN,
    )


def datum_from_msg(msg: Any) -> Datum:
    """sensor_msgs/NavSatFix -> Datum (radians, m)."""
    return Datum(
        math.radians(float(msg.latitude)), math.radians(float(msg.longitude)), float(msg.altitude)
    )


def diagnostics_to_msg(
    types: MsgTypes,
    t: float,
    name: str,
    level: int,
    message: str,
    values: Mapping[str, object],
    hardware_id: str = "",
) -> Any:
    """diagnostic_msgs/DiagnosticArray with one DiagnosticStatus (level 0 OK, 1 WARN, 2 ERROR,
    3 STALE); values become KeyValue pairs (str of each value)."""
    status = types.DiagnosticStatus(
        level=types._byte(level),
        name=str(name),
        message=str(message),
        hardware_id=str(hardware_id),
        values=[types.KeyValue(key=str(k), value=str(v)) for k, v in values.items()],
    )
    return types.DiagnosticArray(header=_header(types, t, ""), status=[status])


def body_rates_from_quats(t: ArrayLike, quat_nb: ArrayLike) -> NDArray[np.float64]:
    """Body angular rate (rad/s, base_link, relative to map) by differencing attitudes:
    omega_b[i] = rotvec(q[i-1]^-1 q[i]) / (t[i] - t[i-1]); the first sample copies the second."""
    t = np.asarray(t, dtype=np.float64)
    q = np.asarray(quat_nb, dtype=np.float64).reshape(-1, 4)
    out = np.zeros((len(t), 3))
    if len(t) < 2:
        return out
    dq = quat_mul(quat_conj(q[:-1]), q[1:])
    dt = np.diff(t)
    safe = np.where(dt > 0, dt, 1.0)
    out[1:] = np.where((dt > 0)[:, None], rotvec_from_quat(dq) / safe[:, None], 0.0)
    out[0] = out[1]
    return out
