"""Shared helpers for the I/O tests (no tests here): synthetic logs, trajectories and bags
written with rosbags' own rosbag2 writer."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pipe_nav_core.geo.attitude import quat_from_euler
from pipe_nav_core.geo.earth import enu_to_geodetic
from pipe_nav_core.types import (
    Datum,
    ImuSamples,
    MagSamples,
    Marker,
    OdometerSamples,
    SensorLog,
    Trajectory,
)

DATUM = Datum(math.radians(52.1), math.radians(5.2), 40.0)


def make_log(
    seconds: float = 20.0,
    t0: float = 1000.0,
    imu_hz: int = 100,
    odo_hz: int = 20,
    mag_hz: int = 10,
    seed: int = 0,
    n_markers: int = 3,
) -> SensorLog:
    """A random but well-formed sensor log with times on exact nanosecond grids."""
    rng = np.random.default_rng(seed)
    n = int(seconds * imu_hz)
    ti = t0 + np.arange(1, n + 1) / imu_hz
    no = int(seconds * odo_hz)
    to = t0 + np.arange(1, no + 1) / odo_hz
    nm = int(seconds * mag_hz)
    tm = t0 + np.arange(1, nm + 1) / mag_hz
    markers = [
        Marker(
            f"agm_{k:02d}",
            round(t0 + (k + 0.5) * seconds / max(n_markers, 1), 3),
            math.radians(52.1 + 0.001 * k),
            math.radians(5.2 + 0.002 * k),
            40.0 + k,
            (0.02, 0.03, 0.04),
        )
        for k in range(n_markers)
    ]
    return SensorLog(
        imu=ImuSamples(
            ti,
            rng.normal(scale=0.1, size=(n, 3)),
            rng.normal(size=(n, 3)) + np.array([0, 0, 9.81]),
        ),
        odometer=OdometerSamples(to, np.cumsum(rng.uniform(0, 0.1, no)), rng.uniform(0, 2, no)),
        mag=MagSamples(tm, rng.normal(scale=2e-5, size=(nm, 3))),
        markers=markers,
    )


def make_traj(n: int = 2001, seconds: float = 200.0, with_sigma: bool = True) -> Trajectory:
    """A gently curving 1 m/s line with a stop between 100 and 110 s, in geodetic terms."""
    t = np.linspace(0.0, seconds, n)
    speed = np.where((t > 100.0) & (t < 110.0), 0.0, 1.0)
    s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))])
    e = 0.8 * s + 3.0 * np.sin(s / 20.0)
    nn = 0.6 * s
    u = -2.0 + 0.5 * np.sin(s / 30.0)
    lat, lon, h = enu_to_geodetic(np.stack([e, nn, u], 1), DATUM.lat, DATUM.lon, DATUM.alt)
    az = np.arctan2(np.gradient(e), np.gradient(nn) + 1e-12)
    q = quat_from_euler(0.1 * np.sin(t / 7.0), 0.05 * np.cos(t / 9.0), np.mod(az, 2 * np.pi))
    vel = np.stack([np.gradient(e, t), np.gradient(nn, t), np.gradient(u, t)], 1)
    sig = (
        np.stack([0.01 + 0.001 * s, 0.02 + 0.001 * s, 0.005 + 0.0005 * s], 1)
        if with_sigma
        else None
    )
    return Trajectory(t, lat, lon, h, vel, q, s, sig, None)


def write_rosbags_dir(
    path: Path,
    messages: list[tuple[str, str, int, object]],
    *,
    version: int = 9,
) -> Path:
    """Write a rosbag2 directory with rosbags' MCAP storage writer.

    messages: (topic, msgtype, log_time_ns, message object or raw CDR bytes) in writing order.
    """
    from pipe_nav_core.io.rosmsg import jazzy_typestore
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = jazzy_typestore()
    with Writer(path, version=version, storage_plugin=StoragePlugin.MCAP) as w:
        conns: dict[str, object] = {}
        for topic, msgtype, _, _ in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
        for topic, msgtype, ns, msg in messages:
            raw = msg if isinstance(msg, bytes) else bytes(ts.serialize_cdr(msg, msgtype))
            w.write(conns[topic], ns, raw)
    return path


def log_messages(log: SensorLog, imu_frame: str = "imu_link") -> list[tuple[str, str, int, object]]:
    """The log as (topic, type, log_time_ns, rosbags message), in time order."""
    from pipe_nav_core.io import rosmsg
    from pipe_nav_core.io.stamps import sec_to_ns_scalar

    types = rosmsg.rosbags_types()
    out: list[tuple[str, str, int, object]] = []
    for i, t in enumerate(log.imu.t):
        m = rosmsg.imu_to_msg(types, t, log.imu.gyro[i], log.imu.accel[i], imu_frame)
        out.append(("/imu/data", "sensor_msgs/msg/Imu", sec_to_ns_scalar(t), m))
    for i, t in enumerate(log.odometer.t):
        m = rosmsg.wheel_to_msg(types, t, log.odometer.distance[i], log.odometer.speed[i])
        out.append(("/odom/wheel", "nav_msgs/msg/Odometry", sec_to_ns_scalar(t), m))
    for i, t in enumerate(log.mag.t):
        m = rosmsg.mag_to_msg(types, t, log.mag.field[i], imu_frame)
        out.append(("/imu/mag", "sensor_msgs/msg/MagneticField", sec_to_ns_scalar(t), m))
    for mk in log.markers:
        m = rosmsg.marker_to_msg(types, mk)
        out.append(("/markers", "sensor_msgs/msg/NavSatFix", sec_to_ns_scalar(mk.t), m))
    out.sort(key=lambda x: x[2])
    return out


def assert_logs_equal(a: SensorLog, b: SensorLog) -> None:
    """Bit-exact equality of two logs (times, values, markers)."""
    np.testing.assert_array_equal(a.imu.t, b.imu.t)
    np.testing.assert_array_equal(a.imu.gyro, b.imu.gyro)
    np.testing.assert_array_equal(a.imu.accel, b.imu.accel)
    np.testing.assert_array_equal(a.odometer.t, b.odometer.t)
    np.testing.assert_array_equal(a.odometer.distance, b.odometer.distance)
    np.testing.assert_array_equal(a.odometer.speed, b.odometer.speed)
    np.testing.assert_array_equal(a.mag.t, b.mag.t)
    np.testing.assert_array_equal(a.mag.field, b.mag.field)
    assert [(m.name, m.t) for m in a.markers] == [(m.name, m.t) for m in b.markers]
    for ma, mb in zip(a.markers, b.markers, strict=True):
        # radians -> degrees (in the message) -> radians: equal to a few ulp
        assert abs(ma.lat - mb.lat) < 1e-15 and abs(ma.lon - mb.lon) < 1e-15
        assert ma.alt == mb.alt
        np.testing.assert_allclose(ma.sigma_enu, mb.sigma_enu, rtol=1e-12)


def test_target_stem_undoes_staging():
    """A document written to a staging path names itself after its target (the GeoJSON and
    KML of pipe-nav smooth were named '.sample_centerline.geojson.b7be8e0b')."""
    from pipe_nav_core.io.atomic import target_stem

    for name in ("a.geojson", "dir/.a.geojson.0123abcd.part", ".a.kml.89abcdef.tmp"):
        assert target_stem(name) == "a"
    assert target_stem(".hidden.geojson") == ".hidden"
