"""Offline smoothing of a recorded bag with smoother_node.

    ros2 launch pipe_nav_ros smooth.launch.py bag:=run.mcap output:=run_smoothed.mcap
    ros2 launch pipe_nav_ros smooth.launch.py bag:=run.mcap csv:=centreline.csv exit_when_done:=true

smoother_node writes <output> like ``pipe-nav smooth`` and publishes /pipe_nav/path,
/pipe_nav/datum and /pipe_nav/bends latched. The estimator settings are the ekf_node section
of config/ekf.yaml (ekf_params:= to use another file). The launch ends when the node exits
(exit_when_done:=true, or a failure).
"""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "pipe_nav_ros"
PATH_ARGUMENTS = ("bag", "output", "markers_csv", "csv", "geojson", "kml", "plot")


def _arg(context, name):
    return LaunchConfiguration(name).perform(context)


def estimator_parameters(path):
    """The estimator settings of the ekf_node (or /**) ros__parameters section of an ekf.yaml
    file, as a dict (ekf_node's own settings such as publish_tf left out)."""
    from pipe_nav_ros.params import IMU_OVERRIDES_PREFIX, nav_param_specs

    names = {spec.name for spec in nav_param_specs()} | {IMU_OVERRIDES_PREFIX.rstrip(".")}
    with open(path, encoding="utf-8") as f:
        data = yaml.safe_load(f) or {}
    for key in ("ekf_node", "/ekf_node", "/**"):
        section = data.get(key)
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            return {k: v for k, v in section["ros__parameters"].items() if k in names}
    raise RuntimeError(f"{path}: no ekf_node: ros__parameters: section")


def _actions(context):
    if not _arg(context, "bag"):
        raise RuntimeError("smooth.launch.py needs bag:=<input .mcap file or bag directory>")
    params = {name: _arg(context, name) for name in PATH_ARGUMENTS}
    params["method"] = _arg(context, "method")
    params["iterations"] = int(_arg(context, "iterations"))
    params["spacing"] = float(_arg(context, "spacing"))
    params["exit_when_done"] = _arg(context, "exit_when_done").strip().lower() in (
        "1",
        "true",
        "yes",
    )
    return [
        Node(
            package=PACKAGE,
            executable="smoother_node",
            name="smoother_node",
            output="screen",
            parameters=[estimator_parameters(_arg(context, "ekf_params")), params],
            on_exit=Shutdown(reason="smoother_node exited"),
        )
    ]


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    arguments = [
        ("bag", "", "input bag: .mcap file or rosbag2 directory (required)"),
        ("output", "", "output .mcap (default <bag stem>_smoothed.mcap beside the bag)"),
        ("method", "rts", "smoother: rts | two-filter | forward | graph (smooth --method)"),
        ("iterations", "5", "smoothing passes at most (they stop once converged)"),
        ("spacing", "0.5", "centreline sample spacing, m of chainage"),
        ("markers_csv", "", "marker CSV adding to or replacing /markers"),
        ("csv", "", "centreline CSV output"),
        ("geojson", "", "GeoJSON output"),
        ("kml", "", "KML output"),
        ("plot", "", "plot output (png/pdf/svg)"),
        ("exit_when_done", "false", "exit after publishing (else keep the latched path up)"),
        ("ekf_params", os.path.join(share, "config", "ekf.yaml"), "estimator parameter file"),
    ]
    return LaunchDescription(
        [DeclareLaunchArgument(n, default_value=d, description=h) for n, d, h in arguments]
        + [OpaqueFunction(function=_actions)]
    )
