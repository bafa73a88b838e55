"""ekf_node under real rclpy: warmed before it is ready, QoS, faults in /diagnostics, load.

Skipped where rclpy is missing. Each test has its own rclpy Context on its own ROS domain (the
load benchmark's ekf_node is a separate process on another domain of its own), spins one
SingleThreadedExecutor from the test thread, and cleans up after itself.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="rclpy (ROS 2 Jazzy) is not installed here")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from pipe_nav_ros.ekf_core import WARN  # noqa: E402
from pipe_nav_ros.ekf_node import EkfNode  # noqa: E402
from pipe_nav_ros.msg_types import rclpy_types  # noqa: E402
from pipe_nav_ros.params import nav_params_from_config  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import (  # noqa: E402
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from ros_graph import own_domain, spin_until  # noqa: E402
from sensor_msgs.msg import Imu, MagneticField, NavSatFix  # noqa: E402

from pipe_nav_core import NavConfig, rosmsg, simulate, write_markers_csv  # noqa: E402
from pipe_nav_ros import ekf_node as ekf_node_module  # noqa: E402


def qos(reliability, depth=5000, durability=DurabilityPolicy.VOLATILE) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=reliability,
        durability=durability,
    )


RELIABLE = qos(ReliabilityPolicy.RELIABLE)
BEST_EFFORT = qos(ReliabilityPolicy.BEST_EFFORT)
LATCHED = qos(ReliabilityPolicy.RELIABLE, 1, DurabilityPolicy.TRANSIENT_LOCAL)
TOPICS = {"imu": "/imu/data", "odometer": "/odom/wheel", "mag": "/imu/mag", "markers": "/markers"}
TYPES = {"imu": Imu, "odometer": Odometry, "mag": MagneticField, "markers": NavSatFix}


@pytest.fixture(scope="module")
def run():
    return simulate("demo", 0)


@pytest.fixture
def survey_csv(run, tmp_path):
    path = tmp_path / "survey.csv"
    write_markers_csv(path, run.log.markers)
    return path


def ekf(graph, ctx, run, **extra):
    cfg = NavConfig.from_dict(run.scenario.estimator_settings())
    values = {**nav_params_from_config(cfg), "publish_tf": False, **extra}
    params = [Parameter(k, value=v) for k, v in values.items() if v is not None]
    node = EkfNode(context=ctx, parameter_overrides=params)
    executor, _, nodes = graph
    executor.add_node(node)
    nodes.append(node)
    return node


def values_of(status) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


# ------------------------------------------------------------------------------ start-up


def test_kernels_are_warmed_before_the_node_subscribes(ctx, graph, run, monkeypatch):
    """warm_live runs in the node's start-up, before any subscription exists."""
    events = []
    monkeypatch.setattr(ekf_node_module, "_KERNELS_READY_S", None)  # as in a fresh process
    real_warm = ekf_node_module.warm_live

    def warm():
        events.append("warm")
        return real_warm()

    real_subscribe = EkfNode.create_subscription

    def subscribe(self, *args, **kwargs):
        events.append(f"subscribe {args[1]}")
        return real_subscribe(self, *args, **kwargs)

    monkeypatch.setattr(ekf_node_module, "warm_live", warm)
    monkeypatch.setattr(EkfNode, "create_subscription", subscribe)
    node = ekf(graph, ctx, run)
    assert events[0] == "warm" and "warm" not in events[1:]
    assert {e.split()[1] for e in events[1:]} >= {"imu/data", "odom/wheel", "imu/mag", "markers"}
    assert node.warmup_s > 0
    # a second node in the same process does not warm again
    events.clear()
    ekf(graph, ctx, run)
    assert "warm" not in events


# ------------------------------------------------------------------------------ QoS


def counted(node, sent):
    return {r: node.core.counters[r].received for r in sent}


def test_sensor_inputs_receive_from_reliable_and_best_effort_publishers(ctx, graph, run):
    executor, helper, _ = graph
    node = ekf(graph, ctx, run)
    types = rclpy_types()
    sent = {"imu": 0, "odometer": 0, "mag": 0}
    t = 0.0
    for profile in (RELIABLE, BEST_EFFORT):
        pubs = {role: helper.create_publisher(TYPES[role], TOPICS[role], profile) for role in sent}
        assert spin_until(
            executor, lambda p=pubs: all(x.get_subscription_count() for x in p.values())
        )
        for k in range(100):
            t += 0.01
            pubs["imu"].publish(rosmsg.imu_to_msg(types, t, [0.0, 0.0, 0.0], [0.0, 0.0, 9.8]))
            sent["imu"] += 1
            if k % 5 == 0:
                pubs["odometer"].publish(rosmsg.wheel_to_msg(types, t, 0.0, 0.0))
                pubs["mag"].publish(rosmsg.mag_to_msg(types, t, [2e-5, 0.0, -4e-5]))
                sent["odometer"] += 1
                sent["mag"] += 1
            if k % 10 == 9:  # best effort: let the node keep up
                spin_until(executor, lambda: node.core.counters["imu"].received >= sent["imu"], 2)
        assert spin_until(executor, lambda: counted(node, sent) == sent), counted(node, sent)
    engine = node.core.nav.diagnostics()
    assert engine["received_imu"] == sent["imu"] == 200
    assert engine["received_odometer"] == sent["odometer"] and engine["received_mag"] == sent["mag"]
    assert all(n == 0 for c in node.core.counters.values() for n in c.faults.values())


def test_markers_from_volatile_and_latched_reliable_publishers(ctx, graph, run):
    executor, helper, _ = graph
    node = ekf(graph, ctx, run)
    types = rclpy_types()
    for k, durability in enumerate((DurabilityPolicy.VOLATILE, DurabilityPolicy.TRANSIENT_LOCAL)):
        pub = helper.create_publisher(
            NavSatFix, "/markers", qos(ReliabilityPolicy.RELIABLE, 100, durability)
        )
        assert spin_until(executor, lambda p=pub: p.get_subscription_count() > 0)
        pub.publish(rosmsg.marker_to_msg(types, run.log.markers[k]))
        assert spin_until(executor, lambda n=k + 1: node.core.counters["markers"].received == n)


def test_latched_datum_reaches_a_late_subscriber(ctx, graph, run, survey_csv):
    """With a survey the datum is known at start and published latched; a transient-local
    subscriber that joins afterwards gets it, a volatile one does not."""
    executor, helper, _ = graph
    node = ekf(graph, ctx, run, survey_markers_csv=str(survey_csv))
    assert spin_until(executor, lambda: node.core._datum_sent is not None)
    spin_until(executor, lambda: False, 0.5)  # the datum was published some time ago
    late, volatile = [], []
    helper.create_subscription(NavSatFix, "/pipe_nav/datum", late.append, LATCHED)
    helper.create_subscription(
        NavSatFix, "/pipe_nav/datum", volatile.append, qos(ReliabilityPolicy.RELIABLE, 1)
    )
    assert spin_until(executor, lambda: late, 10.0)
    spin_until(executor, lambda: False, 0.5)
    assert volatile == []  # what transient local adds
    first = run.log.markers[0]
    # the survey CSV holds 9 decimals of a degree
    assert late[0].latitude == pytest.approx(math.degrees(first.lat), abs=1e-9)
    assert late[0].longitude == pytest.approx(math.degrees(first.lon), abs=1e-9)


# ------------------------------------------------------------------------------ faults


def test_faults_are_named_in_diagnostics_and_the_estimates_stay_finite(ctx, graph, run, survey_csv):
    """Malformed messages among 15 s of the demo run (100 Hz IMU, published at up to 10x real
    time), then a burst: the sensors of the next 5 s, the IMU at 1 kHz (5000 messages, with the
    odometer's 250 and the magnetometer's 100), published at once.
    The node keeps running, counts every message, names each kind of fault in /diagnostics
    (WARN) and keeps publishing finite estimates."""
    executor, helper, _ = graph
    node = ekf(
        graph,
        ctx,
        run,
        survey_markers_csv=str(survey_csv),
        sensor_qos_depth=5000,
        diagnostics_period_s=0.25,
    )
    odometry, diagnostics = [], []
    helper.create_subscription(Odometry, "/pipe_nav/odometry", odometry.append, RELIABLE)
    helper.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 100)
    pubs = {role: helper.create_publisher(TYPES[role], TOPICS[role], RELIABLE) for role in TOPICS}
    assert spin_until(executor, lambda: all(p.get_subscription_count() for p in pubs.values()))
    types = rclpy_types()

    def bad(t: float) -> list[tuple[str, object]]:
        def imu(stamp=t, gyro=(0.0, 0.0, 0.0), frame_id="imu_link"):
            return rosmsg.imu_to_msg(types, stamp, gyro, [0.0, 0.0, 9.8], frame_id=frame_id)

        odo = rosmsg.wheel_to_msg(types, t, 0.0, 0.0)
        odo.header.frame_id = "map"
        marker = rosmsg.marker_to_msg(types, run.log.markers[-1])
        marker.header.frame_id = ""
        return [
            ("imu", imu(gyro=(math.nan, 0.0, 0.0))),
            ("imu", imu(frame_id="odom")),
            ("imu", imu(frame_id="")),
            ("imu", imu(stamp=t + 1000.0)),
            ("imu", imu(stamp=t - 5.0)),
            ("odometer", odo),
            ("mag", rosmsg.mag_to_msg(types, t, [math.inf, 0.0, 0.0])),
            ("markers", marker),
        ]

    normal = rosmsg.log_to_messages(types, run.log, 15.0)
    fast = simulate("demo", 0, imu_rate_hz=1000.0).log  # the same run, a 1 kHz IMU
    burst = [m for m in rosmsg.log_to_messages(types, fast, 20.0)
             if m[0] > 15.0 and m[1] != "markers"]  # fmt: skip
    imu_at = [k for k, m in enumerate(normal) if m[1] == "imu"]
    inject = {imu_at[len(imu_at) // 3], imu_at[2 * len(imu_at) // 3]}
    sent = dict.fromkeys(TOPICS, 0)

    def publish(role, msg):
        pubs[role].publish(msg)
        sent[role] += 1

    def received():
        return {r: node.core.counters[r].received for r in TOPICS}

    start = time.monotonic()
    for k, (t, role, msg) in enumerate(normal):
        if k in inject:
            for bad_role, bad_msg in bad(t):
                publish(bad_role, bad_msg)
            msg.angular_velocity_covariance[0] = -1.0  # a negative variance: kept
        publish(role, msg)
        if k % 20 == 19:  # no backlog (the executor would let the slower topics run ahead)
            spin_until(executor, lambda: received() == sent, 5.0)
            while time.monotonic() < start + t / 10.0:  # at most 10x real time: no burst
                executor.spin_once(timeout_sec=0.002)
    assert spin_until(executor, lambda: received() == sent, 20.0), (received(), sent)
    # the node published as it went; what it published is heard a little later
    delivered = lambda: len(odometry) == node.core.estimates_published  # noqa: E731
    assert spin_until(executor, delivered, 10.0), (len(odometry), node.core.estimates_published)
    before_burst = len(odometry)
    for _, role, msg in burst:  # 5 s of data at once
        publish(role, msg)
    assert spin_until(executor, lambda: received() == sent, 30.0), (received(), sent)
    spin_until(executor, lambda: False, 1.0)  # estimates and diagnostics after the burst
    assert spin_until(executor, delivered, 10.0), (len(odometry), node.core.estimates_published)

    faults = {r: c.faults for r, c in node.core.counters.items()}
    expected = {
        "imu.fault.nan": 2,
        "imu.fault.frame_id": 4,
        "imu.fault.stamp_future": 2,
        "imu.fault.stamp_past": 2,
        "imu.fault.covariance": 2,
        "odometer.fault.frame_id": 2,
        "mag.fault.nan": 2,
        "markers.fault.frame_id": 2,
    }
    for key, n in expected.items():
        role, _, kind = key.split(".")
        assert faults[role][kind] == n, key
    assert faults["imu"]["burst"] > 0
    # each kind named in a WARN status, counted under its key
    assert spin_until(executor, lambda: diagnostics, 5.0)
    statuses = [s for a in diagnostics for s in a.status if s.name == "pipe_nav: ekf_node"]
    last = values_of(statuses[-1])
    for key in [*expected, "imu.fault.burst"]:
        assert int(last[key]) == faults[key.split(".")[0]][key.split(".")[2]], key
        assert any(s.level == bytes([WARN]) and key in s.message for s in statuses), key
    assert float(last["imu.received"]) == sent["imu"]
    # the node kept running: estimates all along, past the far-future stamp and the burst
    assert before_burst > 50 and len(odometry) > before_burst + 30  # 10 Hz, 4.5 s
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in odometry]
    assert max(stamps) > 18.0
    pos = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z]
                    for m in odometry])  # fmt: skip
    assert np.all(np.isfinite(pos))
    assert np.all(np.isfinite([m.pose.covariance[0] for m in odometry]))
    latency = [float(values_of(s)["latency_ms.max"]) for s in statuses]
    assert any(math.isfinite(v) and v > 0 for v in latency)  # latency is reported


# ------------------------------------------------------------------------------ load


def test_load_benchmark_short_run(tmp_path):
    """The load benchmark's function for 5 s: ekf_node as a real process under a 1 kHz IMU
    from this one; no IMU message dropped, estimates published (no latency threshold here:
    that is the benchmark's, BENCHMARKS.md)."""
    from pipe_nav_ros.bench_load import markdown, run_bench, write_section

    result = run_bench(5.0, workdir=tmp_path, domain_id=own_domain(), ready_timeout_s=600.0)
    assert result["published"]["imu"] == 5001
    assert result["dropped"] == {"imu": 0, "odometer": 0, "mag": 0, "markers": 0}, result
    assert result["estimates_received"] > 10
    assert math.isfinite(result["latency_ms_median"]) and result["realtime_headroom"] > 0
    assert result["faults"] == {}
    # warmed before ready: its log says so, in this order
    log = (tmp_path / "ekf_node.log").read_text()
    order = [
        log.find(s) for s in ("loading the numeric kernels", "kernels ready", "ekf_node ready")
    ]
    assert -1 not in order and order == sorted(order), log
    # the Markdown section replaces itself in place
    bench = tmp_path / "BENCHMARKS.md"
    bench.write_text("# B\n\n## Other\n\ntext\n")
    text = markdown(result, "python -m pipe_nav_ros.bench_load --duration 5")
    write_section(bench, text)
    write_section(bench, text)
    content = bench.read_text()
    assert content.count("## ROS 2: ekf_node under a 1 kHz IMU") == 1
    assert content.startswith("# B\n\n## Other\n\ntext\n")
    bench.write_text(content + "\n## Last\n\nend\n")  # a section after it
    write_section(bench, text)
    content = bench.read_text()
    assert content.count("## ROS 2: ekf_node under a 1 kHz IMU") == 1
    assert content.endswith("moments when the machine held the node up.\n\n## Last\n\nend\n")


def test_ctrl_c_under_a_message_stream_is_a_clean_stop(ctx, graph, run, tmp_path):
    """ros2 launch delivers Ctrl-C twice, often while a callback converts a message: ekf_node
    exits 0 without a traceback every time."""
    import signal
    import subprocess

    executor, helper, _ = graph
    env = {**os.environ, "ROS_DOMAIN_ID": str(ctx.get_domain_id())}
    pub = helper.create_publisher(Imu, "/imu/data", BEST_EFFORT)
    msgs = [
        m for _, role, m in rosmsg.log_to_messages(rclpy_types(), run.log, 30.0) if role == "imu"
    ]
    for attempt in range(3):
        proc = subprocess.Popen(["ros2", "run", "pipe_nav_ros", "ekf_node"], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)  # fmt: skip
        try:
            assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 120.0)
            for k, msg in enumerate(msgs[:2000]):
                pub.publish(msg)
                if k == 1000 + 300 * attempt:
                    os.killpg(proc.pid, signal.SIGINT)
                    os.killpg(proc.pid, signal.SIGINT)
            out, _ = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        assert proc.returncode == 0 and "Traceback" not in out, out[-2000:]
