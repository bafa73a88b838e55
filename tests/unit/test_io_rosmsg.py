"""ROS message conversion helpers (with rosbags' classes standing in for rclpy's)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pipe_nav_core.geo.attitude import quat_from_euler
from pipe_nav_core.geo.earth import enu_to_geodetic
from pipe_nav_core.io import rosmsg as R
from pipe_nav_core.io.rosmsg import jazzy_typestore
from pipe_nav_core.types import Marker
from test_io_support import DATUM, make_traj

TYPES = R.rosbags_types()
TS = jazzy_typestore()


def _roundtrip(msg, typename):
    """Serialize with rosbags (fails if a field is missing or mistyped) and read back."""
    return TS.deserialize_cdr(bytes(TS.serialize_cdr(msg, typename)), typename)


@pytest.mark.parametrize(
    ("t", "sec", "nsec"),
    [
        (0.0, 0, 0),
        (1.5, 1, 500_000_000),
        (-1.7, -2, 300_000_000),
        (-0.000000001, -1, 999_999_999),
        (1.9999999999, 2, 0),  # rounds to the nearest ns, carrying into sec
        (1_700_000_000.25, 1_700_000_000, 250_000_000),
    ],
)
def test_stamps_exact_and_negative_safe(t, sec, nsec):
    s = R.sec_to_stamp(TYPES, t)
    assert (s.sec, s.nanosec) == (sec, nsec)
    assert isinstance(s.sec, int) and isinstance(s.nanosec, int)  # rclpy insists on int
    assert R.stamp_to_ns(s) == sec * 10**9 + nsec
    if abs(t) < 1e6:
        assert R.stamp_to_sec(s) == pytest.approx(t, abs=1e-9)


def test_imu_wheel_mag_messages():
    m = R.imu_to_msg(
        TYPES, 12.25, [0.1, -0.2, 0.3], [0.0, 0.5, 9.8], gyro_var=1e-6, accel_var=[1e-4, 2e-4, 3e-4]
    )
    back = _roundtrip(m, "sensor_msgs/msg/Imu")
    t, g, a = R.imu_from_msg(back)
    assert t == 12.25
    np.testing.assert_array_equal(g, [0.1, -0.2, 0.3])
    np.testing.assert_array_equal(a, [0.0, 0.5, 9.8])
    assert back.orientation_covariance[0] == -1.0
    assert back.header.frame_id == "imu_link"
    assert back.angular_velocity_covariance[4] == 1e-6
    assert back.linear_acceleration_covariance[8] == 3e-4
    assert back.linear_acceleration_covariance[1] == 0.0

    w = _roundtrip(R.wheel_to_msg(TYPES, 3.0, 101.5, 1.25), "nav_msgs/msg/Odometry")
    assert R.wheel_from_msg(w) == (3.0, 101.5, 1.25)
    assert (w.header.frame_id, w.child_frame_id) == ("odom", "base_link")
    assert w.pose.pose.position.y == 0.0 and w.twist.twist.angular.z == 0.0

    g = _roundtrip(
        R.mag_to_msg(TYPES, 4.0, [2e-5, -1e-5, 4e-5], "imu_link"), "sensor_msgs/msg/MagneticField"
    )
    t, f = R.mag_from_msg(g)
    assert t == 4.0
    np.testing.assert_array_equal(f, [2e-5, -1e-5, 4e-5])


def test_marker_messages_and_default_sigma():
    mk = Marker("agm_07", 321.5, math.radians(51.5), math.radians(-0.12), 12.3, (0.02, 0.03, 0.05))
    msg = _roundtrip(R.marker_to_msg(TYPES, mk), "sensor_msgs/msg/NavSatFix")
    assert msg.header.frame_id == "agm_07"
    assert msg.latitude == pytest.approx(51.5, abs=1e-12)
    assert msg.position_covariance_type == R.COVARIANCE_TYPE_DIAGONAL_KNOWN
    back = R.marker_from_msg(msg)
    assert back.name == "agm_07" and back.t == 321.5
    assert back.lat == pytest.approx(mk.lat, abs=1e-15)
    np.testing.assert_allclose(back.sigma_enu, mk.sigma_enu, rtol=1e-12)
    msg.position_covariance_type = R.COVARIANCE_TYPE_UNKNOWN
    assert R.marker_from_msg(msg).sigma_enu == (0.05, 0.05, 0.05)
    msg.position_covariance_type = R.COVARIANCE_TYPE_DIAGONAL_KNOWN
    msg.position_covariance = np.zeros(9)
    assert R.marker_from_msg(msg).sigma_enu == (0.05, 0.05, 0.05)


def test_log_to_messages_in_stamp_order_up_to_t_end():
    from pipe_nav_core.sim import simulate

    log = simulate("demo", 0).log
    types = R.rosbags_types()
    msgs = R.log_to_messages(types, log, t_end=12.0)
    stamps = [t for t, _, _ in msgs]
    assert stamps == sorted(stamps) and stamps[-1] <= 12.0
    roles = [r for _, r, _ in msgs]
    assert roles.count("imu") == int(np.sum(log.imu.t <= 12.0))
    assert roles.count("odometer") == int(np.sum(log.odometer.t <= 12.0))
    assert roles.count("mag") == int(np.sum(log.mag.t <= 12.0))
    assert roles.count("markers") == sum(m.t <= 12.0 for m in log.markers) >= 1
    t, gyro, accel = R.imu_from_msg(next(m for _, r, m in msgs if r == "imu"))
    np.testing.assert_allclose(gyro, log.imu.gyro[0])
    assert R.stamp_to_sec(next(m for _, r, m in msgs if r == "markers").header.stamp) <= 12.0


def test_odometry_position_relative_to_datum_and_body_twist():
    # a point 100 m east, 50 m north, 2 m up of the datum
    lat, lon, h = enu_to_geodetic(np.array([100.0, 50.0, 2.0]), DATUM.lat, DATUM.lon, DATUM.alt)
    # heading east (azimuth 90 deg), nose up 10 deg
    q = quat_from_euler(0.0, math.radians(10.0), math.radians(90.0))
    vel_n = np.array([2.0 * math.cos(math.radians(10)), 0.0, 2.0 * math.sin(math.radians(10))])
    cov6 = np.diag([0.01, 0.02, 0.03, 1e-4, 2e-4, 3e-4])
    m = R.odometry_to_msg(
        TYPES, 7.0, DATUM, float(lat), float(lon), float(h), q, vel_n, [0.0, 0.0, 0.1], cov6
    )
    back = _roundtrip(m, "nav_msgs/msg/Odometry")
    d = R.odometry_from_msg(back)
    assert (d["frame_id"], d["child_frame_id"]) == ("map", "base_link")
    np.testing.assert_allclose(d["position"], [100.0, 50.0, 2.0], atol=1e-6)
    np.testing.assert_allclose(d["vel_b"], [2.0, 0.0, 0.0], atol=1e-12)  # all forward
    np.testing.assert_allclose(d["omega_b"], [0.0, 0.0, 0.1])
    np.testing.assert_array_equal(d["pose_cov"], cov6)
    np.testing.assert_allclose(d["quat"], q)
    assert d["t"] == 7.0
    # variances as a 6-vector work too; twist covariance defaults to zeros
    m2 = R.odometry_to_msg(
        TYPES, 7.0, DATUM, DATUM.lat, DATUM.lon, DATUM.alt, q, vel_n, np.zeros(3), np.arange(6.0)
    )
    assert np.asarray(m2.pose.covariance).reshape(6, 6)[5, 5] == 5.0
    np.testing.assert_allclose(R.odometry_from_msg(m2)["position"], 0.0, atol=1e-9)
    assert not np.any(m2.twist.covariance)


def test_path_datum_and_diagnostics():
    traj = make_traj(n=21, seconds=2.0)
    p = _roundtrip(R.path_to_msg(TYPES, traj, DATUM), "nav_msgs/msg/Path")
    assert p.header.frame_id == "map" and len(p.poses) == 21
    t, enu, q = R.path_from_msg(p)
    np.testing.assert_allclose(t, traj.t, atol=1e-9)
    np.testing.assert_allclose(q, traj.quat_nb)
    assert R.stamp_to_sec(p.header.stamp) == pytest.approx(traj.t[-1])

    dm = _roundtrip(R.datum_to_msg(TYPES, DATUM, 5.0), "sensor_msgs/msg/NavSatFix")
    assert dm.header.frame_id == "map"
    assert dm.latitude == pytest.approx(52.1, abs=1e-12) and dm.altitude == 40.0
    back = R.datum_from_msg(dm)
    assert back.lat == pytest.approx(DATUM.lat, abs=1e-15)

    diag = R.diagnostics_to_msg(TYPES, 9.0, "pipe_nav/ekf", 1, "slow IMU", {"imu_hz": 99.5, "n": 3})
    d = _roundtrip(diag, "diagnostic_msgs/msg/DiagnosticArray")
    st = d.status[0]
    assert (st.level, st.name, st.message) == (1, "pipe_nav/ekf", "slow IMU")
    assert [(kv.key, kv.value) for kv in st.values] == [("imu_hz", "99.5"), ("n", "3")]


def test_byte_fields_for_rclpy_style_classes():
    # rclpy classes have no __msgtype__: byte fields must then be bytes of length 1
    class FakeStatus:
        def __init__(self, **kw):
            self.__dict__.update(kw)

    types = R.MsgTypes(**{**TYPES.__dict__, "DiagnosticStatus": FakeStatus, "byte_as_bytes": None})
    st = R.diagnostics_to_msg(types, 0.0, "x", 2, "err", {}).status[0]
    assert st.level == b"\x02"


def test_body_rates_from_quats():
    t = np.linspace(0.0, 1.0, 11)
    q = quat_from_euler(np.zeros(11), np.zeros(11), -0.5 * t)  # yaw left at 0.5 rad/s
    w = R.body_rates_from_quats(t, q)
    np.testing.assert_allclose(w, np.tile([0.0, 0.0, 0.5], (11, 1)), atol=1e-9)
