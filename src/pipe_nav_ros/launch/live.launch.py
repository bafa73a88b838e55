"""Live navigation: the three sensor drivers and ekf_node.

    ros2 launch pipe_nav_ros live.launch.py                       # simulated demo run
    ros2 launch pipe_nav_ros live.launch.py source:=serial \\
        imu_port:=/dev/ttyUSB0 odometer_port:=/dev/ttyUSB1 mag_port:=/dev/ttyUSB2
    ros2 launch pipe_nav_ros live.launch.py source:=log \\
        imu_log:=imu.csv odometer_log:=odo.csv mag_log:=mag.csv markers_csv:=markers.csv

Driver parameters come from config/drivers.yaml, estimator parameters from config/ekf.yaml
(override with driver_params:= / ekf_params:=). ekf_node starts first; the drivers start when it
says it is ready (its numeric kernels loaded, which takes seconds), so the estimator sees the
data from the first sample on (the static alignment needs the rest at the start). In log and
sim mode the drivers share one start time, startup_delay after that, so the three streams are
replayed in step.
"""

import os
import time

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, LogInfo, OpaqueFunction, RegisterEventHandler
from launch.event_handlers import OnProcessIO
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "pipe_nav_ros"
EKF_READY = b"ekf_node ready"  # ekf_node's log line once it takes data


def _arg(context, name):
    return LaunchConfiguration(name).perform(context)


def _truthy(text):
    return text.strip().lower() in ("1", "true", "yes", "on")


def _drivers(context):
    """The driver nodes, their start time startup_delay from now (system time)."""
    source = _arg(context, "source")
    rate = float(_arg(context, "rate"))
    start_time = time.time() + float(_arg(context, "startup_delay"))
    driver_params = _arg(context, "driver_params")
    common = {
        "source": source,
        "rate": rate,
        "start_time": start_time,
        "scenario": _arg(context, "scenario"),
        "seed": int(_arg(context, "seed")),
        "baud": int(_arg(context, "baud")),
    }
    drivers = [
        ("imu_driver_node", "imu_port", "imu_log", {}),
        (
            "odometer_driver_node",
            "odometer_port",
            "odometer_log",
            {"markers_csv": _arg(context, "markers_csv")},
        ),
    ]
    if _truthy(_arg(context, "use_mag")):
        drivers.append(("magnetometer_driver_node", "mag_port", "mag_log", {}))
    actions = []
    for executable, port_arg, log_arg, extra in drivers:
        log_file = _arg(context, log_arg)
        if source == "log" and not log_file and executable == "magnetometer_driver_node":
            continue  # no magnetometer log: run without it
        params = dict(common, port=_arg(context, port_arg), log_file=log_file, **extra)
        actions.append(
            Node(
                package=PACKAGE,
                executable=executable,
                name=executable,
                output="screen",
                parameters=[driver_params, params],
            )
        )
    return actions


def _nodes(context):
    """ekf_node, and a handler that starts the drivers once ekf_node is ready."""
    for name, kind in (("rate", float), ("startup_delay", float), ("seed", int), ("baud", int)):
        kind(_arg(context, name))  # a bad number fails the launch now, not at ekf_node's ready
    ekf = Node(
        package=PACKAGE,
        executable="ekf_node",
        name="ekf_node",
        output="screen",
        parameters=[
            _arg(context, "ekf_params"),
            {"publish_tf": _truthy(_arg(context, "publish_tf"))},
        ],
    )
    started = []

    def on_output(event):
        if started or EKF_READY not in event.text:
            return None
        started.append(True)
        return [
            LogInfo(msg="ekf_node ready: starting the drivers"),
            OpaqueFunction(function=_drivers),
        ]

    handler = OnProcessIO(target_action=ekf, on_stdout=on_output, on_stderr=on_output)
    return [RegisterEventHandler(handler), ekf]


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    arguments = [
        ("source", "sim", "sensor source of the three drivers: serial | log | sim"),
        ("use_mag", "true", "run the magnetometer driver"),
        ("scenario", "demo", "sim: scenario of pipe_nav_core.sim"),
        ("seed", "0", "sim: random seed"),
        ("rate", "1.0", "log/sim: playback speed factor"),
        (
            "startup_delay",
            "8.0",
            "log/sim: seconds from ekf_node being ready (the drivers' start) to the first sample",
        ),
        ("imu_port", "/dev/ttyUSB0", "serial: IMU device"),
        ("odometer_port", "/dev/ttyUSB1", "serial: odometer device"),
        ("mag_port", "/dev/ttyUSB2", "serial: magnetometer device"),
        ("baud", "115200", "serial: baud rate of the three devices"),
        ("imu_log", "", "log: IMU CSV log (t_s,gx,gy,gz,ax,ay,az)"),
        ("odometer_log", "", "log: odometer CSV log (t_s,ticks)"),
        ("mag_log", "", "log: magnetometer CSV log (t_s,mx,my,mz); empty = no magnetometer"),
        ("markers_csv", "", "log: marker passages CSV published on /markers"),
        ("publish_tf", "true", "ekf_node broadcasts TF map -> base_link"),
        ("ekf_params", os.path.join(share, "config", "ekf.yaml"), "ekf_node parameter file"),
        ("driver_params", os.path.join(share, "config", "drivers.yaml"), "driver parameter file"),
    ]
    return LaunchDescription(
        [DeclareLaunchArgument(n, default_value=d, description=h) for n, d, h in arguments]
        + [OpaqueFunction(function=_nodes)]
    )
