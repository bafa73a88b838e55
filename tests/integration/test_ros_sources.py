"""pipe_nav_ros driver logic without ROS: line protocol, CSV logs, calibration, timing, messages.

Messages are built with rosbags' Jazzy classes and serialized to CDR, so what the drivers
publish is known to be valid sensor_msgs / nav_msgs for Jazzy.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from pipe_nav_ros.driver_core import MARKER, SENSOR, DriverCore
from pipe_nav_ros.params import driver_param_specs, driver_settings_from_params
from pipe_nav_ros.sources import (
    CSV_COLUMNS,
    DeviceClockSync,
    ImuSample,
    LineAssembler,
    MagCalibration,
    MagSample,
    OdoSample,
    ProtocolError,
    ReadStats,
    Scales,
    TickOdometer,
    TickSample,
    Timeline,
    format_line,
    log_samples,
    merge_by_time,
    nmea_checksum,
    parse_line,
    play,
    read_csv_log,
    sim_samples,
)

from pipe_nav_core import ConfigError, Marker, rosmsg

TYPES = rosmsg.rosbags_types()


def roundtrip(msg, typename):
    """Serialize with the Jazzy typestore and read back (fails on an invalid message)."""
    ts = rosmsg.jazzy_typestore()
    return ts.deserialize_cdr(ts.serialize_cdr(msg, typename), typename)


# ------------------------------------------------------------------------------ line protocol


def test_parse_imu_line_with_and_without_checksum():
    body = "PNIMU,12.5,0.01,-0.02,0.03,0.1,0.2,9.81"
    line = f"${body}*{nmea_checksum(body)}\r\n"
    s = parse_line(line, "imu")
    assert isinstance(s, ImuSample)
    assert s.t == 12.5
    assert s.gyro == (0.01, -0.02, 0.03)
    assert s.accel == (0.1, 0.2, 9.81)
    assert parse_line(f"${body}\n".encode(), "imu") == s  # bytes, no checksum
    assert parse_line(f"${body}*{nmea_checksum(body).lower()}", "imu") == s


def test_parse_line_scales_units():
    s = parse_line("$PNIMU,1,90,0,0,1,0,0", "imu", Scales(gyro=math.pi / 180, accel=9.80665))
    assert s.gyro[0] == pytest.approx(math.pi / 2)
    assert s.accel[0] == pytest.approx(9.80665)
    m = parse_line("$PNMAG,2.0,20,-5,40", "mag")  # microtesla by default
    assert isinstance(m, MagSample)
    assert m.field == pytest.approx((20e-6, -5e-6, 40e-6))


def test_parse_odometer_line():
    s = parse_line("$PNODO,3.25,-1234", "odometer")
    assert s == TickSample(3.25, -1234)
    with pytest.raises(ProtocolError, match="integer"):
        parse_line("$PNODO,3.25,12.5", "odometer")


@pytest.mark.parametrize(
    "line, why",
    [
        ("$PNIMU,1,2,3*00", "checksum"),
        ("$PNIMU,1,2,3,4,5,6", "7 fields"),
        ("$PNIMU,1,nan,0,0,0,0,9.8", "not finite"),
        ("$PNIMU,1,x,0,0,0,0,9.8", "not a number"),
        ("PNIMU,1,0,0,0,0,0,9.8", "start with"),
        ("$GPGGA,1,2", "unknown sentence"),
    ],
)
def test_parse_line_rejects_damaged_lines(line, why):
    with pytest.raises(ProtocolError, match=why):
        parse_line(line, "imu")


def test_parse_line_skips_other_sensors_comments_and_blanks():
    assert parse_line("$PNODO,1.0,5", "imu") is None
    assert parse_line("# device banner", "imu") is None
    assert parse_line("   \r\n", "mag") is None


def test_format_line_round_trips():
    scales = Scales(gyro=0.5, accel=2.0, field=1e-6)
    for kind, sample in (
        ("imu", ImuSample(0.123456789, (0.1, -0.2, 0.3), (0.4, 0.5, 9.7))),
        ("odometer", TickSample(7.5, 987654)),
        ("mag", MagSample(1e6 + 0.25, (2e-5, -3e-6, 4.5e-5))),
    ):
        line = format_line(sample, scales)
        assert line.endswith("\r\n")
        back = parse_line(line, kind, scales)
        assert back.t == sample.t
        for a, b in zip(
            np.ravel([getattr(back, f) for f in ("gyro", "accel") if hasattr(back, f)]),
            np.ravel([getattr(sample, f) for f in ("gyro", "accel") if hasattr(sample, f)]),
            strict=True,
        ):
            assert a == pytest.approx(b, rel=1e-12)


def test_line_assembler_handles_fragments_crlf_and_garbage():
    la = LineAssembler(max_length=40)
    assert la.feed(b"$PNODO,1.0,") == []
    assert la.feed(b"5\r\n$PNODO,2.0,6\r") == [b"$PNODO,1.0,5"]
    assert la.feed(b"\n") == [b"$PNODO,2.0,6"]
    assert la.feed(b"x" * 100) == []  # no newline, too long: dropped
    assert la.overlong == 1
    assert la.feed(b"y" * 100) == []  # still the same line: dropped, not counted again
    assert la.feed(b"yy\n$PNODO,3.0,7\n") == [b"$PNODO,3.0,7"]  # its end dropped too
    assert la.overlong == 1
    assert la.feed(b"z" * 41 + b"\n\n") == [b""]  # complete and too long
    assert la.overlong == 2


# ------------------------------------------------------------------------------ CSV logs


def test_csv_log_with_header_comments_and_bad_rows():
    text = "\n".join(
        [
            "# recorder v2",
            "t_s,gx,gy,gz,ax,ay,az",
            "0.00,0,0,0,0,0,9.8",
            "0.01,0.1,0,0,0,0,9.8",
            "0.01,0.2,0,0,0,0,9.8",  # same time: skipped
            "0.02,bad,0,0,0,0,9.8",  # malformed
            "",
            "0.03,0.3,0,0,0,0,9.8",
        ]
    )
    stats = ReadStats()
    errors = []
    samples = list(
        read_csv_log(io.StringIO(text), "imu", Scales(), stats, lambda n, w: errors.append(n))
    )
    assert [s.t for s in samples] == [0.0, 0.01, 0.03]
    assert stats.samples == 3 and stats.malformed == 1 and stats.non_increasing == 1
    assert errors == [5, 6]


def test_csv_log_without_header_and_wrong_header():
    samples = list(read_csv_log(io.StringIO("1.0,10\n2.0,20\n"), "odometer"))
    assert samples == [TickSample(1.0, 10), TickSample(2.0, 20)]
    with pytest.raises(ConfigError, match="t_s,ticks"):
        list(read_csv_log(io.StringIO("t_s,gx,gy,gz,ax,ay,az\n"), "odometer"))


def test_log_samples_reads_a_file(tmp_path):
    path = tmp_path / "mag.csv"
    path.write_text("t_s,mx,my,mz\n0.0,20,0,-40\n0.05,21,0,-40\n")
    samples = list(log_samples(path, "mag"))
    assert len(samples) == 2 and samples[1].field[0] == pytest.approx(21e-6)
    with pytest.raises(ConfigError, match="does not exist"):
        list(log_samples(tmp_path / "missing.csv", "mag"))
    assert CSV_COLUMNS["mag"] == ("t_s", "mx", "my", "mz")


# ------------------------------------------------------------------------------ calibration


def test_tick_odometer_distance_and_speed():
    odo = TickOdometer(circumference_m=0.5, ticks_per_turn=1000, speed_window_s=0.1)
    assert odo.update(10.0, 5000) == (0.0, 0.0)  # distance counts from the first sample
    out = [odo.update(10.0 + 0.02 * k, 5000 + 80 * k) for k in range(1, 11)]
    # 80 ticks per 20 ms = 0.04 m per 20 ms = 2 m/s
    assert out[-1][0] == pytest.approx(10 * 80 * 0.5 / 1000)
    assert all(v == pytest.approx(2.0) for _, v in out)
    # reversing for a whole window: negative speed
    for k in range(1, 7):
        d, v = odo.update(10.2 + 0.02 * k, 5800 - 40 * k)
    assert d == pytest.approx(0.4 - 6 * 0.02) and v == pytest.approx(-1.0)


def test_tick_odometer_unwraps_counter():
    odo = TickOdometer(1.0, 100, 0.2, counter_bits=16)
    odo.update(0.0, 65530)
    d, _ = odo.update(0.1, 4)  # wrapped by +10 ticks
    assert d == pytest.approx(0.1)
    d, _ = odo.update(0.2, 65534)  # back by 6 ticks across the wrap
    assert d == pytest.approx(0.04)


@pytest.mark.parametrize(
    "args, name",
    [
        ((0.0, 100), "wheel_circumference_m"),
        ((0.5, 0), "ticks_per_turn"),
        ((0.5, 10, -1.0), "speed_window_s"),
    ],
)
def test_tick_odometer_refuses_bad_calibration(args, name):
    with pytest.raises(ConfigError, match=name):
        TickOdometer(*args)


def test_mag_calibration():
    cal = MagCalibration(hard_iron=(1e-6, -2e-6, 0.5e-6), soft_iron=(2, 0, 0, 0, 1, 0, 0, 0, 0.5))
    assert cal.apply((11e-6, 8e-6, 40.5e-6)) == pytest.approx((20e-6, 10e-6, 20e-6))
    with pytest.raises(ConfigError, match="soft_iron"):
        MagCalibration(soft_iron=(1.0, 0.0))


# ------------------------------------------------------------------------------ time


def test_device_clock_sync_follows_least_delay_and_resets():
    sync = DeviceClockSync(max_drift=1e-4)
    assert sync.stamp(100.0, 1000.020) == pytest.approx(1000.020)  # first: offset 900.02
    assert sync.stamp(100.1, 1000.105) == pytest.approx(1000.105)  # smaller delay wins
    assert sync.stamp(100.2, 1000.290) == pytest.approx(1000.205, abs=1e-4)  # late arrival ignored
    assert sync.stamp(5.0, 2000.0) == pytest.approx(2000.0)  # device clock reset


def test_timeline_pacing_and_stamps():
    tl = Timeline(t_ref=10.0, start=1000.0, rate=2.0, restamp=False)
    assert tl.due(12.0) == 1001.0 and tl.stamp(12.0) == 12.0
    tl = Timeline(t_ref=10.0, start=1000.0, rate=2.0, restamp=True)
    assert tl.stamp(12.0) == 1002.0


def test_play_emits_on_time_and_stops():
    clock = [0.0]
    emitted = []

    def stop(timeout):
        clock[0] += timeout  # a fake clock: waiting advances it
        return False

    samples = [OdoSample(t, t, 1.0) for t in (0.0, 0.5, 1.0)]
    n = play(
        samples,
        Timeline(0.0, 5.0, 1.0, True),
        lambda s, st: emitted.append((clock[0], st)),
        stop,
        now=lambda: clock[0],
    )
    assert n == 3
    assert [st for _, st in emitted] == [5.0, 5.5, 6.0]
    assert all(at >= st - 1e-9 for at, st in emitted)
    assert (
        play(samples, Timeline(0.0, 100.0), lambda s, st: None, lambda t: True, now=lambda: 0.0)
        == 0
    )


def test_merge_by_time_interleaves_markers():
    odo = [OdoSample(t, 0.0, 0.0) for t in (0.0, 1.0, 2.0)]
    mk = [Marker("agm_00", 0.5, 0.7, 2.0, 10.0)]
    assert [s.t for s in merge_by_time(odo, mk)] == [0.0, 0.5, 1.0, 2.0]


# ------------------------------------------------------------------------------ settings


def test_driver_settings_defaults_and_auto_stamps():
    for kind in ("imu", "odometer", "mag"):
        s = driver_settings_from_params(kind, {})
        assert s["source"] == "sim" and s["stamps"] == "clock" and s["kind"] == kind
    assert driver_settings_from_params("imu", {"source": "serial"})["stamps"] == "synced"
    s = driver_settings_from_params("imu", {"source": "log", "log_file": "x.csv", "rate": 2})
    assert s["stamps"] == "source" and s["rate"] == 2.0  # an integer is fine for a double


@pytest.mark.parametrize(
    "values, name",
    [
        ({"source": "usb"}, "source"),
        ({"source": "log"}, "log_file"),
        ({"rate": 0.0}, "rate"),
        ({"rate": True}, "rate"),
        ({"stamps": "synced"}, "synced"),
        ({"baud": "fast"}, "baud"),
        ({"angular_velocity_variance": -1.0}, "angular_velocity_variance"),
    ],
)
def test_driver_settings_refuse_bad_values(values, name):
    with pytest.raises(ConfigError, match=name):
        driver_settings_from_params("imu", values)


def test_driver_param_specs_are_unique():
    for kind in ("imu", "odometer", "mag"):
        names = [s.name for s in driver_param_specs(kind)]
        assert len(names) == len(set(names))


# ------------------------------------------------------------------------------ messages


def core(kind, **values):
    return DriverCore(driver_settings_from_params(kind, values), TYPES)


def test_imu_message():
    c = core("imu", angular_velocity_variance=1e-6, frame_id="imu_front")
    [(role, msg)] = c.messages(ImuSample(5.0, (0.1, 0.2, 0.3), (0.0, 0.1, 9.8)), 1234.5)
    assert role == SENSOR
    msg = roundtrip(msg, "sensor_msgs/msg/Imu")
    assert msg.header.frame_id == "imu_front"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1234, 500_000_000)
    t, g, a = rosmsg.imu_from_msg(msg)
    assert t == 1234.5 and g.tolist() == [0.1, 0.2, 0.3] and a.tolist() == [0.0, 0.1, 9.8]
    assert msg.orientation_covariance[0] == -1.0
    assert np.diag(msg.angular_velocity_covariance.reshape(3, 3)).tolist() == [1e-6] * 3
    assert not msg.linear_acceleration_covariance.any()


def test_odometer_message_from_ticks_and_from_distance():
    c = core("odometer", wheel_circumference_m=0.4, ticks_per_turn=400, speed_window_s=0.05)
    c.messages(TickSample(1.0, 100), 1.0)
    [(_, msg)] = c.messages(TickSample(1.1, 600), 1.1)
    msg = roundtrip(msg, "nav_msgs/msg/Odometry")
    assert msg.header.frame_id == "odom" and msg.child_frame_id == "base_link"
    t, d, v = rosmsg.wheel_from_msg(msg)
    assert (t, d, v) == pytest.approx((1.1, 0.5, 5.0))
    [(_, msg)] = c.messages(OdoSample(2.0, 12.0, 1.5), 2.0)  # simulator: distance given
    assert rosmsg.wheel_from_msg(msg) == pytest.approx((2.0, 12.0, 1.5))


def test_mag_message_is_calibrated():
    c = core("mag", hard_iron=[1e-6, 0, 0], soft_iron=[1, 0, 0, 0, 2, 0, 0, 0, 1])
    [(_, msg)] = c.messages(MagSample(3.0, (21e-6, 5e-6, -40e-6)), 3.0)
    msg = roundtrip(msg, "sensor_msgs/msg/MagneticField")
    assert msg.header.frame_id == "imu_link"
    assert rosmsg.mag_from_msg(msg)[1] == pytest.approx([20e-6, 10e-6, -40e-6])


def test_marker_message_is_restamped():
    c = core("odometer")
    m = Marker("agm_03", 62.0, math.radians(39.9), math.radians(116.4), 45.0, (0.02, 0.02, 0.05))
    [(role, msg)] = c.messages(m, 1_700_000_062.0)
    assert role == MARKER
    back = rosmsg.marker_from_msg(roundtrip(msg, "sensor_msgs/msg/NavSatFix"))
    assert back.name == "agm_03" and back.t == pytest.approx(1_700_000_062.0)
    assert back.lat == pytest.approx(m.lat) and back.sigma_enu == pytest.approx(m.sigma_enu)


# ------------------------------------------------------------------------------ sources


def test_sim_sources_share_the_time_origin():
    imu, t_imu = sim_samples("imu", "demo", 0)
    odo, t_odo = sim_samples("odometer", "demo", 0)
    mag, t_mag = sim_samples("mag", "demo", 0)
    assert t_imu == t_odo == t_mag
    for stream in (imu, odo, mag):
        t = np.array([s.t for s in stream])
        assert len(t) > 100 and np.all(np.diff(t) >= 0)
    markers = [s for s in odo if isinstance(s, Marker)]
    assert len(markers) >= 2
    with pytest.raises(ConfigError, match="scenario"):
        sim_samples("imu", "no_such_scenario", 0)


def test_readme_example_line_parses():
    from pathlib import Path

    readme = (
        Path(__file__).resolve().parents[2] / "src" / "pipe_nav_ros" / "README.md"
    ).read_text()
    line = next(w.strip("`") for w in readme.split() if w.startswith("`$PNIMU,12.500"))
    sample = parse_line(line, "imu")
    assert sample.t == 12.5 and sample.accel[2] == 9.806
