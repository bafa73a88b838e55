"""The rclpy message classes in the shape :mod:`pipe_nav_core.io.rosmsg` converts with."""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

# MsgTypes field -> ROS 2 interface package and message name
ROS_MESSAGES: dict[str, tuple[str, str]] = {
    "Time": ("builtin_interfaces", "Time"),
    "Duration": ("builtin_interfaces", "Duration"),
    "Header": ("std_msgs", "Header"),
    "Imu": ("sensor_msgs", "Imu"),
    "MagneticField": ("sensor_msgs", "MagneticField"),
    "NavSatFix": ("sensor_msgs", "NavSatFix"),
    "NavSatStatus": ("sensor_msgs", "NavSatStatus"),
    "Odometry": ("nav_msgs", "Odometry"),
    "Path": ("nav_msgs", "Path"),
    "PoseStamped": ("geometry_msgs", "PoseStamped"),
    "PoseArray": ("geometry_msgs", "PoseArray"),
    "Pose": ("geometry_msgs", "Pose"),
    "PoseWithCovariance": ("geometry_msgs", "PoseWithCovariance"),
    "Twist": ("geometry_msgs", "Twist"),
    "TwistWithCovariance": ("geometry_msgs", "TwistWithCovariance"),
    "Point": ("geometry_msgs", "Point"),
    "Quaternion": ("geometry_msgs", "Quaternion"),
    "Vector3": ("geometry_msgs", "Vector3"),
    "TransformStamped": ("geometry_msgs", "TransformStamped"),
    "Transform": ("geometry_msgs", "Transform"),
    "DiagnosticArray": ("diagnostic_msgs", "DiagnosticArray"),
    "DiagnosticStatus": ("diagnostic_msgs", "DiagnosticStatus"),
    "KeyValue": ("diagnostic_msgs", "KeyValue"),
}


def rclpy_types() -> Any:
    """A :class:`pipe_nav_core.io.rosmsg.MsgTypes` of the rclpy (rosidl) message classes.

    The message packages are imported here, not at module import, so the module loads without
    ROS. ``byte`` fields are set as ``bytes`` (rclpy's representation). A message field of
    MsgTypes this table does not know raises KeyError (add it to ROS_MESSAGES).
    """
    from pipe_nav_core import rosmsg

    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(rosmsg.MsgTypes):
        if f.name == "byte_as_bytes":
            kwargs[f.name] = True
        elif f.name in ROS_MESSAGES:
            package, name = ROS_MESSAGES[f.name]
            kwargs[f.name] = getattr(importlib.import_module(f"{package}.msg"), name)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise KeyError(f"MsgTypes.{f.name}: no ROS message known for it (see ROS_MESSAGES)")
    return rosmsg.MsgTypes(**kwargs)
