"""The pipe_nav_ros nodes in-process on a ROS 2 Jazzy machine (skipped where rclpy is missing).

Each test starts the nodes in their own rclpy context with parameter overrides and spins one
SingleThreadedExecutor from the test thread, so nothing depends on other processes.
Run after ``colcon build`` and ``source install/setup.bash``:
``python3 -m pytest tests/integration/test_ros_nodes.py -v``.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="rclpy (ROS 2 Jazzy) is not installed here")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry, Path  # noqa: E402
from pipe_nav_ros.driver_node import SensorDriverNode  # noqa: E402
from pipe_nav_ros.ekf_node import EkfNode  # noqa: E402
from pipe_nav_ros.msg_types import rclpy_types  # noqa: E402
from pipe_nav_ros.params import nav_param_specs, nav_params_from_config, params_yaml  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import (  # noqa: E402
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from ros_graph import own_domain, spin_until  # noqa: E402
from sensor_msgs.msg import Imu, MagneticField, NavSatFix  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from pipe_nav_core import (  # noqa: E402
    ConfigError,
    NavConfig,
    SensorLog,
    rosmsg,
    simulate,
    write_sensor_bag,
)

CROP_S = 70.0  # rest, marker agm_00 (10 s), agm_01 (62 s)
LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
RELIABLE = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE
)
# best effort like qos_profile_sensor_data, deep enough not to drop a fast replay while spinning
SENSOR_DEEP = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=5000, reliability=ReliabilityPolicy.BEST_EFFORT
)


def add(graph_, node):
    executor, _, nodes = graph_
    executor.add_node(node)
    nodes.append(node)
    return node


def overrides(values: dict) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items() if value is not None]


@pytest.fixture(scope="module")
def run():
    return simulate("demo", 0)


def scenario_overrides(run, **extra):
    cfg = NavConfig.from_dict(run.scenario.estimator_settings())
    values = nav_params_from_config(cfg)
    values.update(extra)
    return overrides(values)


def input_messages(run, t_end):
    """(stamp, role, message) of the run's first t_end seconds in stamp order."""
    return rosmsg.log_to_messages(rclpy_types(), run.log, t_end)


def call(executor, node, service, timeout=10.0):
    client = node.create_client(Trigger, service)
    assert client.wait_for_service(timeout_sec=timeout), f"{service} not available"
    future = client.call_async(Trigger.Request())
    assert spin_until(executor, future.done, timeout)
    return future.result()


# ------------------------------------------------------------------------------ ekf_node


def test_ekf_node_follows_the_truth_latches_the_datum_and_reports(ctx, graph, run):
    executor, helper, _ = graph
    ekf = add(
        graph,
        EkfNode(
            context=ctx,
            parameter_overrides=scenario_overrides(run, diagnostics_period_s=0.2, publish_tf=True),
        ),
    )

    odometry, diagnostics = [], []
    helper.create_subscription(Odometry, "/pipe_nav/odometry", odometry.append, RELIABLE)
    helper.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 50)
    pubs = {
        "imu": helper.create_publisher(Imu, "/imu/data", qos_profile_sensor_data),
        "odometer": helper.create_publisher(Odometry, "/odom/wheel", qos_profile_sensor_data),
        "mag": helper.create_publisher(MagneticField, "/imu/mag", qos_profile_sensor_data),
        "markers": helper.create_publisher(NavSatFix, "/markers", RELIABLE),
    }
    assert spin_until(executor, lambda: all(p.get_subscription_count() > 0 for p in pubs.values()))

    sent = {role: 0 for role in pubs}
    for k, (_, role, msg) in enumerate(input_messages(run, CROP_S)):
        pubs[role].publish(msg)
        sent[role] += 1
        if k % 20 == 19:  # let the node keep up (best effort drops what overflows)
            spin_until(
                executor,
                lambda: all(ekf.core.counters[r].received >= sent[r] for r in sent),
                timeout=2.0,
            )
    spin_until(executor, lambda: all(ekf.core.counters[r].received >= sent[r] for r in sent), 5.0)
    assert ekf.core.counters["imu"].received > 0.98 * sent["imu"]
    assert ekf.core.counters["markers"].received == sent["markers"]

    response = call(executor, helper, "/ekf_node/finish")
    assert response.success
    spin_until(executor, lambda: False, 1.0)  # collect the flushed estimates
    assert len(odometry) > 100

    truth, d = run.truth, run.datum
    enu = rosmsg.enu_of(d, truth.lat, truth.lon, truth.h)
    errors, stamps = [], []
    for msg in odometry:
        assert msg.header.frame_id == "map" and msg.child_frame_id == "base_link"
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        j = min(int(np.searchsorted(truth.t, t)), len(truth.t) - 1)
        p = msg.pose.pose.position
        errors.append(np.linalg.norm([p.x - enu[j, 0], p.y - enu[j, 1], p.z - enu[j, 2]]))
        stamps.append(t)
        assert msg.pose.covariance[0] > 0 and msg.pose.covariance[35] > 0
    # loose until the second marker re-anchors the heading, then close to the truth
    errors, stamps = np.array(errors), np.array(stamps)
    anchored = stamps > run.log.markers[1].t + 1.0
    assert anchored.sum() > 20 and errors[anchored].max() < 2.0
    assert errors.max() < 100.0

    # latched datum: a subscriber joining now still gets it
    datums = []
    helper.create_subscription(NavSatFix, "/pipe_nav/datum", datums.append, LATCHED)
    assert spin_until(executor, lambda: datums, 5.0)
    assert datums[0].latitude == pytest.approx(math.degrees(run.log.markers[0].lat))

    assert spin_until(executor, lambda: diagnostics, 5.0)
    status = diagnostics[-1].status[0]
    assert status.name == "pipe_nav: ekf_node"
    keys = {kv.key for kv in status.values}
    assert {"imu.rate_hz", "imu.malformed", "markers.received", "engine.state"} <= keys


def test_ekf_node_reports_its_counts_at_the_end_of_data(ctx, graph, run):
    """~/finish publishes a last /diagnostics report before it resets, with every input the
    node received counted (a periodic report can come before the last inputs)."""
    executor, helper, _ = graph
    ekf = add(graph, EkfNode(context=ctx, parameter_overrides=scenario_overrides(
        run, diagnostics_period_s=3600.0)))  # fmt: skip
    diagnostics = []
    helper.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 50)
    pub = helper.create_publisher(Imu, "/imu/data", RELIABLE)
    assert spin_until(executor, lambda: pub.get_subscription_count() > 0)
    imu = [m for _, role, m in input_messages(run, 2.0) if role == "imu"]
    for msg in imu:
        pub.publish(msg)
    assert spin_until(executor, lambda: ekf.core.counters["imu"].received == len(imu), 5.0)
    assert not diagnostics
    assert call(executor, helper, "/ekf_node/finish").success
    assert spin_until(executor, lambda: diagnostics, 5.0)
    values = {kv.key: kv.value for s in diagnostics[-1].status for kv in s.values}
    assert int(values["imu.received"]) == int(values["engine.received_imu"]) == len(imu)


def test_ekf_node_publishes_tf(ctx, graph, run):
    tf2_msgs = pytest.importorskip("tf2_msgs.msg")
    executor, helper, _ = graph
    ekf = add(graph, EkfNode(context=ctx, parameter_overrides=scenario_overrides(run)))
    transforms = []
    helper.create_subscription(tf2_msgs.TFMessage, "/tf", transforms.append, 100)
    for _, role, msg in input_messages(run, 15.0):
        getattr(
            ekf.core,
            {"imu": "on_imu", "odometer": "on_odometer", "mag": "on_mag", "markers": "on_marker"}[
                role
            ],
        )(msg)
    call(executor, helper, "/ekf_node/finish")
    assert spin_until(executor, lambda: transforms, 5.0)
    tf = transforms[0].transforms[0]
    assert tf.header.frame_id == "map" and tf.child_frame_id == "base_link"


def test_ekf_node_reset_service_and_parameter_changes(ctx, graph, run):
    executor, helper, _ = graph
    ekf = add(graph, EkfNode(context=ctx, parameter_overrides=scenario_overrides(run)))
    result = ekf.set_parameters([Parameter("zupt_sigma", value=-1.0)])[0]
    assert not result.successful and "zupt_sigma" in result.reason
    result = ekf.set_parameters([Parameter("zupt_sigma", value=0.0)])[0]  # in the ROS range
    assert not result.successful and "zupt_sigma must be a positive number" in result.reason
    ranges = ekf.describe_parameters(["filter_rate_hz", "gate_probability", "mode"])
    assert [(r.from_value, r.to_value) for r in ranges[0].floating_point_range] == [(0.0, 1000.0)]
    assert [(r.from_value, r.to_value) for r in ranges[1].floating_point_range] == [(0.5, 1.0)]
    assert not ranges[2].floating_point_range
    result = ekf.set_parameters([Parameter("filter_rate_hz", value=20)])[0]  # int for a double
    assert result.successful
    assert ekf.core.config.filter_rate_hz != 20.0  # applied at the reset
    resets = ekf.core.resets
    response = call(executor, helper, "/ekf_node/reset")
    assert response.success and "new parameters" in response.message
    assert ekf.core.resets == resets + 1 and ekf.core.config.filter_rate_hz == 20.0


def test_ekf_node_survives_malformed_messages(ctx, graph, run):
    executor, helper, _ = graph
    ekf = add(graph, EkfNode(context=ctx, parameter_overrides=scenario_overrides(run)))
    pub = helper.create_publisher(Imu, "/imu/data", qos_profile_sensor_data)
    marker_pub = helper.create_publisher(NavSatFix, "/markers", RELIABLE)
    assert spin_until(executor, lambda: pub.get_subscription_count() > 0)
    types = rclpy_types()
    bad = rosmsg.imu_to_msg(types, 1.0, [math.nan, 0.0, 0.0], [0.0, 0.0, math.inf])
    marker = rosmsg.marker_to_msg(types, run.log.markers[0])
    marker.latitude = math.nan
    for _ in range(5):
        pub.publish(bad)
    marker_pub.publish(marker)
    assert spin_until(executor, lambda: ekf.core.nav.diagnostics().get("dropped_nan_imu", 0) >= 1)
    assert spin_until(executor, lambda: ekf.core.counters["markers"].received == 1)
    assert ekf.core.nav.diagnostics().get("dropped_nan_marker", 0) == 1
    executor.spin_once(timeout_sec=0.1)  # still alive


def test_invalid_parameters_refuse_the_node(ctx):
    # outside the declared ROS range: still refused with the settings' own message
    with pytest.raises(ConfigError, match="filter_rate_hz must be a positive number, not -5.0"):
        EkfNode(context=ctx, parameter_overrides=[Parameter("filter_rate_hz", value=-5.0)])
    with pytest.raises(ConfigError, match="gate_probability must be in"):
        EkfNode(context=ctx, parameter_overrides=[Parameter("gate_probability", value=2.0)])
    with pytest.raises(ConfigError, match="mode"):
        EkfNode(context=ctx, parameter_overrides=[Parameter("mode", value="magic")])
    with pytest.raises(ConfigError, match="survey_markers_csv: /nope.csv: cannot read"):
        EkfNode(
            context=ctx, parameter_overrides=[Parameter("survey_markers_csv", value="/nope.csv")]
        )
    with pytest.raises(ConfigError, match="source"):
        SensorDriverNode("imu", context=ctx, parameter_overrides=[Parameter("source", value="usb")])


def test_ekf_node_exits_nonzero_on_invalid_parameters():
    code = "import sys; from pipe_nav_ros.ekf_node import main; sys.exit(main(sys.argv))"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    r = subprocess.run(
        [sys.executable, "-c", code, "--ros-args", "-p", "mode:=magic"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert r.returncode == 2
    assert "mode" in r.stdout + r.stderr and "invalid parameters" in r.stdout + r.stderr


# ------------------------------------------------------------------------------ drivers


def test_rcl_reads_parameter_files_back_the_same(tmp_path):
    """A file of params_yaml given to a node by ``--params-file`` (rcl's own YAML parser) gives
    every NavConfig default and awkward values back with their type ('on' a string)."""
    values = {s.name: s.default for s in nav_param_specs() if s.default is not None}
    values.update(small=1e-5, big=1e20, tenth=0.1, negative_zero=-0.0, int_as_float=1e16,
                  on_string="on", number_string="1e-05", floats=[1e-5, 1e20, -0.0])  # fmt: skip
    path = tmp_path / "params.yaml"
    path.write_text(params_yaml("yaml_check", values))
    context = rclpy.context.Context()
    rclpy.init(args=["--ros-args", "--params-file", str(path)], context=context,
               domain_id=own_domain())  # fmt: skip
    try:
        node = rclpy.create_node(
            "yaml_check", context=context, automatically_declare_parameters_from_overrides=True
        )
        got = {name: p.value for name, p in node.get_parameters_by_prefix("").items()}
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    for name, value in values.items():
        v = list(got[name]) if isinstance(value, list) else got[name]
        assert v == value and type(v) is type(value), (name, got[name])
        if isinstance(value, float) and value == 0.0:
            assert math.copysign(1.0, v) == math.copysign(1.0, value), name


def test_sim_drivers_publish_the_simulated_run(ctx, graph, run):
    executor, helper, _ = graph
    imu_msgs, odo_msgs = [], []
    helper.create_subscription(Imu, "/imu/data", imu_msgs.append, SENSOR_DEEP)
    helper.create_subscription(Odometry, "/odom/wheel", odo_msgs.append, SENSOR_DEEP)
    params = [Parameter("source", value="sim"), Parameter("rate", value=20.0)]
    add(graph, SensorDriverNode("imu", context=ctx, parameter_overrides=params))
    add(graph, SensorDriverNode("odometer", context=ctx, parameter_overrides=params))
    assert spin_until(executor, lambda: len(imu_msgs) > 200 and len(odo_msgs) > 100, 15.0)
    first = imu_msgs[0]
    assert first.header.frame_id == "imu_link"
    now = helper.get_clock().now().nanoseconds * 1e-9
    assert abs(first.header.stamp.sec - now) < 30.0  # moved onto the clock
    k = next(i for i, t in enumerate(run.log.imu.t) if t > 0)  # some sample matches the sim
    gyro = [[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in imu_msgs]
    assert np.min(np.abs(np.array(gyro)[:, 0] - run.log.imu.gyro[k, 0])) < 1e-12
    # the marker passages are latched on /markers: a late subscriber gets agm_00 (t = 10 s)
    markers = []
    helper.create_subscription(
        NavSatFix,
        "/markers",
        markers.append,
        QoSProfile(
            depth=100,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
            reliability=ReliabilityPolicy.RELIABLE,
        ),
    )
    assert spin_until(executor, lambda: markers, 5.0)
    assert markers[0].header.frame_id == "agm_00"


def test_log_driver_replays_a_csv_with_its_own_stamps(ctx, graph, tmp_path):
    executor, helper, _ = graph
    log = tmp_path / "odo.csv"
    log.write_text("t_s,ticks\n" + "".join(f"{100 + 0.02 * k:.2f},{40 * k}\n" for k in range(50)))
    msgs = []
    helper.create_subscription(Odometry, "/odom/wheel", msgs.append, SENSOR_DEEP)
    node = add(
        graph,
        SensorDriverNode(
            "odometer",
            context=ctx,
            parameter_overrides=[
                Parameter("source", value="log"),
                Parameter("log_file", value=str(log)),
                Parameter("rate", value=10.0),
                Parameter("wheel_circumference_m", value=0.5),
                Parameter("ticks_per_turn", value=1000),
                Parameter("exit_when_done", value=True),
            ],
        ),
    )
    assert spin_until(executor, lambda: len(msgs) == 50, 15.0)
    assert msgs[0].header.stamp.sec == 100 and msgs[0].header.frame_id == "odom"
    assert msgs[-1].pose.pose.position.x == pytest.approx(49 * 40 * 0.5 / 1000)
    assert msgs[-1].twist.twist.linear.x == pytest.approx(1.0)
    assert spin_until(executor, lambda: node.exit_code == 0, 5.0)


def test_serial_driver_reads_the_line_protocol(ctx, graph):
    pytest.importorskip("serial", reason="pyserial (python3-serial) is not installed")
    executor, helper, _ = graph
    master, slave = os.openpty()
    msgs = []
    helper.create_subscription(MagneticField, "/imu/mag", msgs.append, SENSOR_DEEP)
    add(
        graph,
        SensorDriverNode(
            "mag",
            context=ctx,
            parameter_overrides=[
                Parameter("source", value="serial"),
                Parameter("port", value=os.ttyname(slave)),
                Parameter("hard_iron", value=[1e-6, 0.0, 0.0]),
            ],
        ),
    )
    from pipe_nav_ros.sources import MagSample, format_line

    time.sleep(0.2)
    os.write(master, b"garbage line\r\n")
    # written slower than the device clock (a late line keeps the offset of the least delayed
    # one): 0.05 s of lag per line, so that the driver reading the first line up to 50 ms later
    # than the next (a loaded machine) cannot lower the offset; with 0.01 s a 10 ms hiccup could
    for k in range(10):
        os.write(master, format_line(MagSample(5.0 + 0.05 * k, (21e-6, 0.0, -40e-6))).encode())
        time.sleep(0.1)
    assert spin_until(executor, lambda: len(msgs) == 10, 10.0)
    assert msgs[0].magnetic_field.x == pytest.approx(20e-6)
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in msgs]
    # device intervals kept (the offset may only grow by the drift allowance, 1e-4 s/s)
    assert np.diff(stamps) == pytest.approx(0.05, abs=1e-4)
    os.close(master)
    os.close(slave)


# ------------------------------------------------------------------------------ smoother_node


def test_smoother_node_publishes_a_latched_path(ctx, graph, run, tmp_path):
    from pipe_nav_ros.smoother_node import SmootherNode

    executor, helper, _ = graph
    log = run.log
    t_end = 90.0
    write_sensor_bag(
        tmp_path / "in.mcap",
        SensorLog(
            imu=log.imu.slice(log.imu.t <= t_end),
            odometer=log.odometer.slice(log.odometer.t <= t_end),
            mag=log.mag.slice(log.mag.t <= t_end),
            markers=[m for m in log.markers if m.t <= t_end],
        ),
    )
    diagnostics = []
    helper.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 50)
    node = add(
        graph,
        SmootherNode(
            context=ctx,
            parameter_overrides=scenario_overrides(
                run,
                bag=str(tmp_path / "in.mcap"),
                output=str(tmp_path / "out.mcap"),
                csv=str(tmp_path / "centreline.csv"),
                diagnostics_period_s=0.2,
            ),
        ),
    )
    assert spin_until(executor, lambda: node.job.state != "running", 120.0), "smoothing too slow"
    assert node.job.state == "done", node.job.error
    assert spin_until(executor, lambda: node._published_at is not None, 5.0)
    paths, datums = [], []
    helper.create_subscription(Path, "/pipe_nav/path", paths.append, LATCHED)  # joins late
    helper.create_subscription(NavSatFix, "/pipe_nav/datum", datums.append, LATCHED)
    assert spin_until(executor, lambda: paths and datums, 10.0)
    assert len(paths[0].poses) > 10 and paths[0].header.frame_id == "map"
    assert (tmp_path / "out.mcap").is_file() and (tmp_path / "centreline.csv").is_file()
    assert any(s.name == "pipe_nav: smoother_node" for a in diagnostics for s in a.status)


def test_smoother_node_refuses_a_missing_bag(ctx):
    from pipe_nav_ros.smoother_node import SmootherNode

    with pytest.raises(ConfigError, match="bag"):
        SmootherNode(context=ctx, parameter_overrides=[Parameter("bag", value="/no/such.mcap")])
