"""The three driver nodes on a real ROS 2 Jazzy (skipped where rclpy is missing).

Each driver is run against a pseudo-terminal serial device (``os.openpty()``: the test writes the
README's line protocol into the master side, the driver opens the slave's tty with pyserial) and
against its recorder CSV log. One test per driver runs it as a real process (``ros2 run
pipe_nav_ros <driver> --ros-args -p ...``, as a user would); the detailed value checks run the
node in-process. Every test has a ROS domain of its own (so parallel runs never see each other),
writes only under tmp_path, and stops what it starts. Values are checked against the README's
formulas: scales, counter unwrapping, hard/soft iron, each ``stamps`` mode, frames, markers.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import re
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="rclpy (ROS 2 Jazzy) is not installed here")

from nav_msgs.msg import Odometry  # noqa: E402
from pipe_nav_ros.driver_node import SensorDriverNode  # noqa: E402
from pipe_nav_ros.sources import nmea_checksum  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from ros_graph import LoggedProcess, ros2_with_workspace, spin_until  # noqa: E402
from sensor_msgs.msg import Imu, MagneticField, NavSatFix  # noqa: E402

from pipe_nav_core import ConfigError, rosmsg  # noqa: E402

SENSOR_DEEP = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=5000, reliability=ReliabilityPolicy.BEST_EFFORT
)
LATCHED_DEEP = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def line(body: str, checksum: bool = True) -> bytes:
    return (f"${body}*{nmea_checksum(body)}\r\n" if checksum else f"${body}\n").encode()


def bad_checksum(body: str) -> bytes:
    """A sentence whose checksum is wrong (the right one with its lowest bit flipped)."""
    return f"${body}*{int(nmea_checksum(body), 16) ^ 1:02X}\r\n".encode()


def stamp(msg) -> float:
    return rosmsg.stamp_to_sec(msg.header.stamp)


@pytest.fixture
def pty():
    """(master fd, slave tty path); the test writes into master, the driver opens the path."""
    pytest.importorskip("serial", reason="pyserial (python3-serial) is not installed")
    master, slave = os.openpty()
    fds = {"master": master, "slave": slave}
    yield fds, os.ttyname(slave)
    for fd in fds.values():
        with contextlib.suppress(OSError):
            os.close(fd)


def start_driver(graph_, ctx, kind, **params):
    executor, _, nodes = graph_
    node = SensorDriverNode(
        kind,
        context=ctx,
        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
    )
    executor.add_node(node)
    nodes.append(node)
    return node


def prime(executor, master: int, msgs: list, probe) -> int:
    """Write ``probe(i)`` lines until one comes through (publisher and subscriber matched both
    ways: best effort drops what is published before), then drop what came; how many were sent."""
    for i in range(200):
        os.write(master, probe(i))
        if spin_until(executor, lambda: msgs, 0.1):
            break
    else:
        raise AssertionError("no probe line came through the driver in 20 s")
    spin_until(executor, lambda: False, 0.2)
    msgs.clear()
    return i + 1


def write_slowly(master: int, chunks, pause: float = 0.03) -> None:
    for chunk in chunks:
        os.write(master, chunk)
        time.sleep(pause)


# ------------------------------------------------------------------------------ processes


def _ros_param(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_ros_param(v) for v in value) + "]"
    return str(value)


class DriverProcess(LoggedProcess):
    """``ros2 run pipe_nav_ros <executable> --ros-args -p k:=v ...`` in its own process group,
    output (the node's log) in a file."""

    def __init__(self, executable: str, params: dict, domain: int, log: Path) -> None:
        ros2 = ros2_with_workspace()
        args = [ros2, "run", "pipe_nav_ros", executable, "--ros-args"]
        for name, value in params.items():
            args += ["-p", f"{name}:={_ros_param(value)}"]
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1")
        super().__init__(args, env, log)

    def wait_for_output(self, text: str, timeout: float = 60.0) -> None:
        self.wait_for(re.escape(text), timeout)

    def interrupt(self, timeout: float = 20.0, times: int = 2) -> int:
        """Ctrl-C as ``ros2 launch`` delivers it (twice); the exit status."""
        return super().interrupt(timeout, times)


@pytest.fixture
def driver_process(ctx, tmp_path):
    """Starts drivers with ros2 run on the test's ROS domain; stops them all at the end."""
    procs: list[DriverProcess] = []

    def start(executable: str, **params) -> DriverProcess:
        p = DriverProcess(
            executable, params, ctx.get_domain_id(), tmp_path / f"{executable}_{len(procs)}.log"
        )
        procs.append(p)
        return p

    yield start
    for p in procs:
        p.stop()


def test_imu_driver_process_reads_a_serial_device(ctx, graph, pty, driver_process):
    """ros2 run imu_driver_node on a pty: raw units times the scales, device stamps (stamps
    source), frame and covariances as set; damaged lines logged and skipped; Ctrl-C exits 0."""
    executor, helper, _ = graph
    fds, port = pty
    msgs: list[Imu] = []
    helper.create_subscription(Imu, "/imu/data", msgs.append, SENSOR_DEEP)
    deg, g = math.pi / 180.0, 9.80665
    proc = driver_process(
        "imu_driver_node",
        source="serial",
        port=port,
        baud=460800,
        stamps="source",
        gyro_scale=deg,  # the device sends deg/s and g
        accel_scale=g,
        frame_id="imu_front",
        angular_velocity_variance=1e-6,
        linear_acceleration_variance=4e-4,
    )
    proc.wait_for_output(f"reading {port} at 460800 baud")
    prime(executor, fds["master"], msgs, lambda i: line(f"PNIMU,{i * 0.001},0,0,0,0,0,1"))
    raw = [(50.0 + 0.01 * k, 1.5 * k, -2.0, 0.25, 0.01 * k, -0.02, 1.0) for k in range(20)]
    chunks = [bad_checksum("PNIMU,1.0,2,3,4,5,6,7")]
    chunks += [b"# device banner\r\n", b"\r\n", line("PNODO,49.99,1234")]  # skipped silently
    for k, r in enumerate(raw):
        text = line("PNIMU," + ",".join(repr(float(x)) for x in r), checksum=k % 2 == 0)
        chunks += [text[:9], text[9:]] if k % 5 == 0 else [text]  # split across reads
    write_slowly(fds["master"], chunks, 0.01)
    assert spin_until(executor, lambda: len(msgs) >= len(raw), 20.0), proc.output()
    spin_until(executor, lambda: False, 0.3)
    assert len(msgs) == len(raw)
    for msg, r in zip(msgs, raw, strict=True):
        assert stamp(msg) == pytest.approx(r[0], abs=1e-9)  # the device's own time
        assert msg.header.frame_id == "imu_front"
        w, a = msg.angular_velocity, msg.linear_acceleration
        assert [w.x, w.y, w.z] == pytest.approx([x * deg for x in r[1:4]], rel=1e-12)
        assert [a.x, a.y, a.z] == pytest.approx([x * g for x in r[4:7]], rel=1e-12)
        assert msg.orientation_covariance[0] == -1.0
        assert list(msg.angular_velocity_covariance[[0, 4, 8]]) == [1e-6] * 3
        assert list(msg.linear_acceleration_covariance[[0, 4, 8]]) == [4e-4] * 3
        assert msg.angular_velocity_covariance[1] == 0.0
    assert "skipped serial line: checksum mismatch" in proc.output()
    assert proc.interrupt() == 0
    assert "Traceback" not in proc.output() and "Exception ignored" not in proc.output()


def _odometer_log(path: Path, n: int, t0: float, dt: float, step: int, first: int) -> list:
    """A 16-bit unsigned counter log that wraps; returns [(t, unwrapped ticks since start)]."""
    rows, truth = ["# recorder 7, odometer channel", "t_s,ticks"], []
    for k in range(n):
        t = t0 + dt * k
        rows.append(f"{t:.3f},{(first + step * k) % 65536}")
        truth.append((round(t, 3), step * k))
        if k == 10:
            rows.append(f"{t + dt / 2:.3f},12.5")  # not an integer count
        if k == 20:
            rows.append(f"{t - dt:.3f},{first}")  # time going backwards
    path.write_text("\n".join(rows) + "\n")
    return truth


def _markers_csv(path: Path, rows) -> None:
    header = "name,time_s,latitude_deg,longitude_deg,altitude_m,sigma_h_m,sigma_v_m\n"
    path.write_text(header + "".join(",".join(str(x) for x in r) + "\n" for r in rows))


def test_odometer_driver_process_replays_a_log_with_markers_and_exits(
    ctx, graph, tmp_path, driver_process
):
    """ros2 run odometer_driver_node on a recorder log: the counter unwrapped, distance and
    speed from the calibration, the markers_csv passages on /markers (latched), damaged rows
    counted, and at the end of the log (exit_when_done) exit status 0."""
    executor, helper, _ = graph
    odo: list[Odometry] = []
    markers: list[NavSatFix] = []
    helper.create_subscription(Odometry, "/odom/wheel", odo.append, SENSOR_DEEP)
    helper.create_subscription(NavSatFix, "/markers", markers.append, LATCHED_DEEP)
    circumference, per_turn = 0.471, 2048
    truth = _odometer_log(tmp_path / "odometer.csv", 100, 2000.0, 0.02, 300, 60000)
    _markers_csv(
        tmp_path / "markers.csv",
        [
            ("launch", 2000.5, 52.1, 4.3, 1.5, 0.1, 0.2),
            ("agm_01", 2001.5, 52.11, 4.31, 2.0, "", ""),
        ],
    )
    proc = driver_process(
        "odometer_driver_node",
        source="log",
        log_file=str(tmp_path / "odometer.csv"),
        markers_csv=str(tmp_path / "markers.csv"),
        wheel_circumference_m=circumference,
        ticks_per_turn=per_turn,
        counter_bits=16,
        speed_window_s=0.1,
        rate=2.0,
        start_time=time.time() + 5.0,  # time to start and to match the subscriptions
        exit_when_done=True,
    )
    assert proc.wait(timeout=90.0) == 0, proc.output()
    out = proc.output()
    assert "source exhausted after 100 samples and 2 markers" in out
    assert "(skipped: 1 malformed, 1 out of order)" in out
    assert "line 14: ticks is not an integer" in out  # the file's line number
    spin_until(executor, lambda: len(odo) >= 100 and len(markers) == 2, 10.0)

    # best effort: check every message that came (nearly all do on one machine) by its stamp
    expected = dict(truth)
    assert len(odo) >= 90 and stamp(odo[-1]) == pytest.approx(truth[-1][0], abs=1e-9)
    metres_per_tick = circumference / per_turn
    speed = 300 * metres_per_tick / 0.02
    for msg in odo:
        ticks = expected[round(stamp(msg), 3)]
        assert msg.pose.pose.position.x == pytest.approx(ticks * metres_per_tick, rel=1e-12)
        if ticks:
            assert msg.twist.twist.linear.x == pytest.approx(speed, rel=1e-9)
        assert msg.header.frame_id == "odom" and msg.child_frame_id == "base_link"
    assert any(expected[round(stamp(m), 3)] + 60000 > 65535 for m in odo)  # after the wrap

    names = [m.header.frame_id for m in markers]
    assert names == ["launch", "agm_01"]
    launch, agm = markers
    assert stamp(launch) == pytest.approx(2000.5, abs=1e-9)  # stamps source: the CSV's times
    assert (launch.latitude, launch.longitude, launch.altitude) == pytest.approx((52.1, 4.3, 1.5))
    assert list(launch.position_covariance[[0, 4, 8]]) == pytest.approx([0.01, 0.01, 0.04])
    assert launch.position_covariance_type == NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    assert list(agm.position_covariance[[0, 4, 8]]) == pytest.approx([0.05**2] * 3)  # empty


def test_magnetometer_driver_process_calibrates_and_reports_a_lost_device(
    ctx, graph, pty, driver_process
):
    """ros2 run magnetometer_driver_node on a pty, nanotesla device, hard and soft iron from
    -p: field = soft_iron (raw x field_scale - hard_iron); stamps clock = arrival on the ROS
    clock; the device going away ends the node with one error line and status 1."""
    executor, helper, _ = graph
    fds, port = pty
    msgs: list[MagneticField] = []
    helper.create_subscription(MagneticField, "/imu/mag", msgs.append, SENSOR_DEEP)
    hard = [2.0e-6, -1.0e-6, 0.5e-6]
    soft = [1.1, 0.05, 0.0, 0.05, 0.9, 0.0, 0.0, 0.0, 1.0]
    proc = driver_process(
        "magnetometer_driver_node",
        source="serial",
        port=port,
        stamps="clock",
        field_scale=1e-9,
        hard_iron=hard,
        soft_iron=soft,
    )
    proc.wait_for_output(f"reading {port}")
    prime(executor, fds["master"], msgs, lambda i: line(f"PNMAG,{i * 0.001},0,0,0"))
    raw = [(7.0 + 0.1 * k, 21000.0 + 100 * k, -3000.0, -42000.0 + 10 * k) for k in range(8)]
    before = time.time()
    write_slowly(fds["master"], [line("PNMAG," + ",".join(str(x) for x in r)) for r in raw])
    assert spin_until(executor, lambda: len(msgs) >= len(raw), 20.0), proc.output()
    after = time.time()
    s = np.array(soft).reshape(3, 3)
    for msg, r in zip(msgs, raw, strict=True):
        want = s @ (np.array(r[1:]) * 1e-9 - np.array(hard))
        f = msg.magnetic_field
        assert [f.x, f.y, f.z] == pytest.approx(list(want), rel=1e-12, abs=1e-18)
        assert msg.header.frame_id == "imu_link"
        assert before - 0.05 <= stamp(msg) <= after + 0.05  # arrival, not the device's 7 s
    stamps = [stamp(m) for m in msgs]
    assert all(b > a for a, b in itertools.pairwise(stamps))

    os.close(fds.pop("master"))  # the device is unplugged
    assert proc.wait(timeout=30.0) == 1, proc.output()
    errors = [ln for ln in proc.output().splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1 and f"serial port {port} failed" in errors[0]
    assert "Traceback" not in proc.output()


@pytest.mark.parametrize(
    ("params", "message"),
    [
        (
            {"source": "serial", "port": "/dev/pipe_nav_no_such_tty"},
            "cannot open serial port '/dev/pipe_nav_no_such_tty' at 115200 baud: "
            "No such file or directory",
        ),
        ({"source": "log", "log_file": "/nonexistent/imu.csv"}, "does not exist"),
    ],
)
def test_driver_process_refuses_an_unusable_source(ctx, driver_process, params, message):
    if params["source"] == "serial":
        pytest.importorskip("serial", reason="pyserial (python3-serial) is not installed")
    proc = driver_process("imu_driver_node", **params)
    assert proc.wait(timeout=60.0) == 2
    out = proc.output()
    errors = [ln for ln in out.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1 and "invalid parameters, not starting" in errors[0], out
    assert message in errors[0] and "Traceback" not in out


def test_driver_process_started_late_warns_and_catches_up(ctx, tmp_path, driver_process):
    """A start_time already passed: the driver says so (naming start_time), sends what is
    overdue at once and ends at the end of the log."""
    rows = "".join(f"{5 + 0.05 * k:.2f},0,0,0,0,0,9.8\n" for k in range(40))
    (tmp_path / "imu.csv").write_text(rows)
    proc = driver_process(
        "imu_driver_node",
        source="log",
        log_file=str(tmp_path / "imu.csv"),
        start_time=time.time() - 60.0,
        exit_when_done=True,
    )
    assert proc.wait(timeout=60.0) == 0, proc.output()
    out = proc.output()
    warnings = [ln for ln in out.splitlines() if "[WARN]" in ln]
    assert len(warnings) == 1 and "after start_time" in warnings[0], out
    assert "source exhausted after 40 samples (skipped: 0 malformed, 0 out of order)" in out


# ------------------------------------------------------------------------------ in-process


@pytest.mark.parametrize("mode", ["source", "clock"])
def test_imu_log_stamps_pacing_scales_and_end(ctx, graph, tmp_path, mode):
    """A recorder IMU log at 5x: stamps source = the log's times, clock = start_time + (t -
    first t); no sample published before it is due; scales applied; exit_when_done."""
    executor, helper, _ = graph
    n, t0, dt, rate = 50, 1000.0, 0.01, 5.0
    rows = [f"{t0 + dt * k:.2f},{k},{-k},{2 * k},0.5,-0.5,{1.0 + k / 100}" for k in range(n)]
    (tmp_path / "imu.csv").write_text("t_s,gx,gy,gz,ax,ay,az\n" + "\n".join(rows) + "\n")
    msgs: list[tuple[float, Imu]] = []
    helper.create_subscription(
        Imu, "/imu/data", lambda m: msgs.append((time.time(), m)), SENSOR_DEEP
    )
    start = time.time() + 1.0
    node = start_driver(
        graph,
        ctx,
        "imu",
        source="log",
        log_file=str(tmp_path / "imu.csv"),
        rate=rate,
        start_time=start,
        stamps=mode,
        gyro_scale=0.001,  # mrad/s
        accel_scale=2.0,
        exit_when_done=mode == "source",
    )
    assert spin_until(executor, lambda: len(msgs) == n, 20.0)
    for k, (received, msg) in enumerate(msgs):
        t = t0 + dt * k
        want = t if mode == "source" else start + (t - t0)
        assert stamp(msg) == pytest.approx(want, abs=1e-6)
        assert received >= start + (t - t0) / rate - 0.005  # never early (lateness: load)
        w, a = msg.angular_velocity, msg.linear_acceleration
        assert [w.x, w.y, w.z] == pytest.approx([0.001 * k, -0.001 * k, 0.002 * k])
        assert [a.x, a.y, a.z] == pytest.approx([1.0, -1.0, 2.0 + k / 50])
    if mode == "source":
        assert spin_until(executor, lambda: node.exit_code == 0, 5.0)
    else:  # exit_when_done false: the node stays up after the end of its log
        spin_until(executor, lambda: False, 0.5)
        assert node.exit_code is None
    assert node.stats.samples == n and node.stats.malformed == 0


def test_odometer_serial_unwraps_a_signed_counter_with_synced_stamps(ctx, pty, graph):
    """A 16-bit signed encoder counter through +32767 -> -32768 and back, on the pty: distance
    unwrapped and scaled, speed over speed_window_s, signed (reversing); stamps synced = the
    device's intervals on the ROS clock."""
    executor, helper, _ = graph
    fds, port = pty
    msgs: list[Odometry] = []
    helper.create_subscription(Odometry, "/odom/wheel", msgs.append, SENSOR_DEEP)
    start_driver(
        graph,
        ctx,
        "odometer",
        source="serial",
        port=port,
        counter_bits=16,
        wheel_circumference_m=0.5,
        ticks_per_turn=1000,
        speed_window_s=0.04,
        frame_id="odom_wheel",
        child_frame_id="pig",
    )
    steps = [500] * 12 + [-250] * 8  # forward through the wrap, then back
    unwrapped = np.concatenate([[0], np.cumsum(steps)]) + 30000
    raw = [int((u + 32768) % 65536 - 32768) for u in unwrapped]  # what the device sends
    assert min(raw) < 0 < max(raw)
    dt = 0.02  # device interval; written slower, as a device's output reaches the host
    # probes: at rest on the first count, earlier device times
    prime(executor, fds["master"], msgs, lambda i: line(f"PNODO,{1.0 + i * 0.001},{raw[0]}"))
    write_slowly(
        fds["master"], [line(f"PNODO,{3.0 + dt * k:.2f},{c}") for k, c in enumerate(raw)], 0.05
    )
    assert spin_until(executor, lambda: len(msgs) >= len(raw), 10.0)
    now = helper.get_clock().now().nanoseconds * 1e-9
    distance = [m.pose.pose.position.x for m in msgs]
    assert distance == pytest.approx(list((unwrapped - unwrapped[0]) * 0.5 / 1000), abs=1e-12)
    speed = [m.twist.twist.linear.x for m in msgs]
    assert speed[5] == pytest.approx(500 * 0.5e-3 / dt)  # a full window of forward steps
    assert speed[-1] == pytest.approx(-250 * 0.5e-3 / dt)
    stamps = np.array([stamp(m) for m in msgs])
    # device intervals: the least-delay offset only grows by the drift allowance (1e-4 s/s);
    # it may shrink when one read came late (load), so check the bound and the typical step
    steps = np.diff(stamps)
    assert steps.max() <= dt * (1 + 1e-4) + 1e-6
    assert np.median(steps) == pytest.approx(dt, abs=1e-5)
    assert abs(stamps[-1] - now) < 2.0  # on the ROS clock, not the device's 3.4 s
    assert msgs[0].header.frame_id == "odom_wheel" and msgs[0].child_frame_id == "pig"


def test_odometer_log_markers_on_the_clock_and_survey_rows(ctx, graph, tmp_path):
    """Log mode, stamps clock: the first log sample is due (and stamped) at start_time; a
    marker passage before the log does not move that (it goes out at once, stamped before
    start_time); markers without a passage time are not published; all are latched."""
    executor, helper, _ = graph
    n, t0, dt = 40, 500.0, 0.05
    (tmp_path / "odo.csv").write_text(
        "".join(f"{t0 + dt * k:.2f},{10 * k}\n" for k in range(n))  # no header row
    )
    _markers_csv(
        tmp_path / "markers.csv",
        [
            ("trap", 499.0, 10.0, 20.0, 3.0, 0.1, 0.1),  # before the log starts
            ("agm_01", 501.0, 10.001, 20.0, 3.0, 0.1, 0.1),
            ("agm_09", "", 10.009, 20.0, 3.0, 0.1, 0.1),  # surveyed, not passed yet
        ],
    )
    odo: list[tuple[float, Odometry]] = []
    helper.create_subscription(
        Odometry, "/odom/wheel", lambda m: odo.append((time.time(), m)), SENSOR_DEEP
    )
    start = time.time() + 1.0
    node = start_driver(
        graph,
        ctx,
        "odometer",
        source="log",
        log_file=str(tmp_path / "odo.csv"),
        markers_csv=str(tmp_path / "markers.csv"),
        stamps="clock",
        start_time=start,
        rate=4.0,
        exit_when_done=True,
    )
    assert spin_until(executor, lambda: len(odo) == n and node.exit_code == 0, 20.0)
    for k, (received, msg) in enumerate(odo):
        assert stamp(msg) == pytest.approx(start + dt * k, abs=1e-6)
        assert received >= start + dt * k / 4.0 - 0.005
    markers: list[NavSatFix] = []  # joins after the end: latched
    helper.create_subscription(NavSatFix, "/markers", markers.append, LATCHED_DEEP)
    assert spin_until(executor, lambda: len(markers) == 2, 10.0)
    spin_until(executor, lambda: False, 0.3)
    assert [m.header.frame_id for m in markers] == ["trap", "agm_01"]
    assert stamp(markers[0]) == pytest.approx(start - 1.0, abs=1e-6)
    assert stamp(markers[1]) == pytest.approx(start + 1.0, abs=1e-6)
    assert markers[1].latitude == pytest.approx(10.001)


def test_mag_log_calibration_and_damaged_rows(ctx, graph, tmp_path):
    """A magnetometer log in microtesla with damaged rows: each counted and skipped, the node
    goes on; published field = soft_iron (raw x 1e-6 - hard_iron) in tesla."""
    executor, helper, _ = graph
    good = [(10.0 + 0.1 * k, 20.0 + k, -5.0, 40.0 - k) for k in range(12)]
    rows = ["t_s,mx,my,mz"]
    for k, r in enumerate(good):
        rows.append(",".join(str(x) for x in r))
        if k == 2:
            rows += ["10.25,1,2", "10.26,a,2,3", "10.27,nan,0,0", "", "# pause"]
        if k == 6:
            rows.append("10.3,1,1,1")  # earlier than the row before
    (tmp_path / "mag.csv").write_text("\n".join(rows) + "\n")
    msgs: list[MagneticField] = []
    helper.create_subscription(MagneticField, "/imu/mag", msgs.append, SENSOR_DEEP)
    hard = [1e-6, 2e-6, -3e-6]
    soft = [0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 2.0]  # a quarter turn and a z gain
    node = start_driver(
        graph,
        ctx,
        "mag",
        source="log",
        log_file=str(tmp_path / "mag.csv"),
        rate=20.0,
        start_time=time.time() + 1.0,
        hard_iron=hard,
        soft_iron=soft,
        frame_id="mag_link",
        exit_when_done=True,
    )
    assert spin_until(executor, lambda: len(msgs) == len(good) and node.exit_code == 0, 20.0)
    assert (node.stats.malformed, node.stats.non_increasing) == (3, 1)
    s = np.array(soft).reshape(3, 3)
    for msg, r in zip(msgs, good, strict=True):
        want = s @ (np.array(r[1:]) * 1e-6 - np.array(hard))
        f = msg.magnetic_field
        assert [f.x, f.y, f.z] == pytest.approx(list(want), abs=1e-15)
        assert stamp(msg) == pytest.approx(r[0], abs=1e-9)
        assert msg.header.frame_id == "mag_link"


def test_serial_damaged_lines_are_counted_and_skipped(ctx, pty, graph):
    """On the pty: garbage, a wrong checksum, missing fields, non-numbers, NaN, an overlong
    line and an unknown sentence are counted as malformed; comments, blank lines and the
    other sensors' sentences are ignored; every good line around them is published."""
    executor, helper, _ = graph
    fds, port = pty
    msgs: list[Imu] = []
    helper.create_subscription(Imu, "/imu/data", msgs.append, SENSOR_DEEP)
    node = start_driver(graph, ctx, "imu", source="serial", port=port, stamps="source")
    probes = prime(executor, fds["master"], msgs, lambda i: line(f"PNIMU,{i * 0.001},0,0,0,0,0,1"))
    bad = [
        b"\x00\xff garbage\r\n",
        bad_checksum("PNIMU,1.5,0,0,0,0,0,9.8"),
        b"$PNIMU,1.5,0,0,0,0,0,9.8*7G\r\n",
        line("PNIMU,1.5,0,0,0,0,9.8"),
        line("PNIMU,1.5,x,0,0,0,0,9.8"),
        line("PNIMU,1.5,nan,0,0,0,0,9.8"),
        b"$PNIMU," + b"1" * 600 + b"\r\n",
        line("GPGGA,1,2,3"),
    ]
    ignored = [b"# hello\r\n", b"\r\n", line("PNMAG,1.5,1,2,3"), line("PNODO,1.5,7")]
    chunks = [line(f"PNIMU,{1.0 + 0.1 * k},0.1,0.2,0.3,0,0,9.8") for k in range(4)]
    write_slowly(fds["master"], chunks[:2] + bad + ignored + chunks[2:], 0.02)
    assert spin_until(executor, lambda: len(msgs) == 4, 10.0)
    spin_until(executor, lambda: False, 0.2)
    assert [stamp(m) for m in msgs] == pytest.approx([1.0, 1.1, 1.2, 1.3])
    assert node.stats.malformed == len(bad)
    assert node.stats.samples == 4 + probes
    assert node.exit_code is None  # still reading


@pytest.mark.parametrize(
    ("kind", "content", "extra", "message"),
    [
        ("imu", "t_s,mx,my,mz\n1,2,3,4\n", {}, "imu log header must be t_s,gx,gy,gz,ax,ay,az"),
        ("mag", "t_s,mx,my,mz\n# nothing yet\n", {}, "holds no mag samples"),
        ("odometer", "1.0,5\n", {"markers_csv": "/no/m.csv"}, "markers_csv: .* cannot read"),
        ("odometer", "1.0,5\n", {"counter_bits": 65}, "counter_bits"),
        ("mag", "1,2,3,4\n", {"soft_iron": [1.0, 0.0]}, "soft_iron"),
    ],
)
def test_log_driver_refuses_unusable_files_at_start(ctx, tmp_path, kind, content, extra, message):
    (tmp_path / "log.csv").write_text(content)
    with pytest.raises(ConfigError, match=message):
        SensorDriverNode(
            kind,
            context=ctx,
            parameter_overrides=[
                Parameter("source", value="log"),
                Parameter("log_file", value=str(tmp_path / "log.csv")),
            ]
            + [Parameter(k, value=v) for k, v in extra.items()],
        )


def test_a_driver_shut_down_while_it_publishes_ends_without_an_error():
    """The launch ends (its context shut down) while the sim source is publishing: the publish
    that finds the context gone ends the source quietly, not as "source failed" (exit 1)."""
    own = rclpy.Context()
    rclpy.init(context=own)
    node = SensorDriverNode(
        "imu",
        context=own,
        parameter_overrides=[Parameter("source", value="sim"), Parameter("rate", value=20.0)],
    )
    try:
        deadline = time.monotonic() + 30.0
        while node.core.published < 50 and time.monotonic() < deadline:
            time.sleep(0.05)  # the source thread publishes on its own
        assert node.core.published >= 50
        own.try_shutdown()  # as at the end of a launch, the source thread still running
        time.sleep(0.3)
        assert node.exit_code != 1
    finally:
        node.close()
        with contextlib.suppress(Exception):
            node.destroy_node()
