"""ekf_node: the online estimator as a ROS 2 node.

Subscribes (relative names, remappable): ``imu/data`` (sensor_msgs/Imu), ``odom/wheel``
(nav_msgs/Odometry), ``imu/mag`` (sensor_msgs/MagneticField) with sensor-data QoS (best effort:
matches any publisher), and ``markers`` (sensor_msgs/NavSatFix, reliable, volatile: matches
reliable publishers, latched or not).

Publishes ``pipe_nav/odometry`` (nav_msgs/Odometry: pose of base_link in map with covariance,
twist in base_link), ``pipe_nav/datum`` (sensor_msgs/NavSatFix, latched: reliable + transient
local), ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, every ``diagnostics_period_s``) and,
with ``publish_tf``, the TF map -> base_link.

Services: ``~/reset`` (std_srvs/Trigger): restart the estimator (applying estimator parameters
changed since start); ``~/finish`` (std_srvs/Trigger): end of data, flush the estimates still
held for reordering, publish them, then restart (used at the end of a bag replay).

All estimator settings are parameters (config/ekf.yaml); invalid values stop the node at start
with a message naming the parameter (exit status 2), and are refused when set at run time.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from pipe_nav_core.config import ConfigError, NavConfig
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, MagneticField, NavSatFix
from std_srvs.srv import Trigger
from tf2_ros import TransformBroadcaster

from .ekf_core import EkfCore, EkfOutput
from .msg_types import rclpy_types
from .params import EKF_NODE_SPECS, ekf_node_settings, nav_config_from_params, nav_param_specs
from .ros_common import (
    PipeNavNode,
    current_values,
    declare,
    latched_qos,
    markers_subscription_qos,
    run_node,
    sensor_qos,
)
from .sources import read_markers_csv

NODE_NAME = "ekf_node"


class EkfNode(PipeNavNode):
    """The ekf_node (see the module docstring). kwargs go to rclpy.node.Node (for example
    ``parameter_overrides``); raises ConfigError for invalid parameters."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._nav_specs = nav_param_specs()
        nav_values = declare(self, self._nav_specs)
        s = ekf_node_settings(declare(self, EKF_NODE_SPECS, read_only=True))
        self.settings = s
        config = nav_config_from_params(nav_values)
        survey = []
        if s["survey_markers_csv"]:
            try:
                survey = read_markers_csv(s["survey_markers_csv"])
            except ConfigError as exc:
                raise ConfigError(f"survey_markers_csv: {exc}") from None
        self._pending_config: NavConfig | None = None
        self.core = EkfCore(
            config,
            rclpy_types(),
            survey,
            map_frame=s["map_frame"],
            base_frame=s["base_frame"],
            on_problem=self._on_problem,
        )

        sensors = sensor_qos(s["sensor_qos_depth"])
        self.create_subscription(Imu, "imu/data", self.core.on_imu, sensors)
        self.create_subscription(Odometry, "odom/wheel", self.core.on_odometer, sensors)
        self.create_subscription(MagneticField, "imu/mag", self.core.on_mag, sensors)
        self.create_subscription(
            NavSatFix, "markers", self.core.on_marker, markers_subscription_qos()
        )

        self.odometry_pub = self.create_publisher(Odometry, "pipe_nav/odometry", 50)
        self.datum_pub = self.create_publisher(NavSatFix, "pipe_nav/datum", latched_qos(1))
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.tf = TransformBroadcaster(self) if s["publish_tf"] else None

        self.create_service(Trigger, "~/reset", self._reset)
        self.create_service(Trigger, "~/finish", self._finish)
        # Wall-clock (steady) timers: they keep running when a replayed /clock stops.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(s["publish_period_s"], self._poll, clock=steady)
        self.create_timer(s["diagnostics_period_s"], self._publish_diagnostics, clock=steady)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f"ekf_node ready: mode {config.mode}, IMU grade {config.imu_grade}, "
            f"{len(survey)} surveyed marker(s), TF {'on' if self.tf else 'off'}"
        )

    # ------------------------------------------------------------------ output
    def _poll(self) -> None:
        self._publish(self.core.poll())

    def _publish(self, out: EkfOutput) -> None:
        if out.datum is not None:
            self.datum_pub.publish(out.datum)
            self.get_logger().info(
                f"datum: lat {out.datum.latitude:.8f} deg, lon {out.datum.longitude:.8f} deg, "
                f"alt {out.datum.altitude:.3f} m"
            )
        for msg in out.odometry:
            self.odometry_pub.publish(msg)
        if self.tf is not None and out.odometry:
            self.tf.sendTransform([self._transform(m) for m in out.odometry])

    @staticmethod
    def _transform(odom: Odometry) -> TransformStamped:
        tf = TransformStamped()
        tf.header = odom.header
        tf.child_frame_id = odom.child_frame_id
        p = odom.pose.pose.position
        tf.transform.translation.x = p.x
        tf.transform.translation.y = p.y
        tf.transform.translation.z = p.z
        tf.transform.rotation = odom.pose.pose.orientation
        return tf

    def _publish_diagnostics(self) -> None:
        stamp = self.get_clock().now().nanoseconds * 1e-9
        self.diagnostics_pub.publish(self.core.diagnostics(stamp, time.monotonic()))

    def _on_problem(self, role: str, text: str) -> None:
        self.get_logger().warning(f"{role}: {text}", throttle_duration_sec=5.0)

    # ------------------------------------------------------------------ services
    def _reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        applied = self._pending_config is not None
        self.core.reset(config=self._pending_config)
        self._pending_config = None
        response.success = True
        response.message = "estimator reset" + (" with the new parameters" if applied else "")
        self.get_logger().info(response.message)
        return response

    def _finish(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        out = self.core.finish(config=self._pending_config)
        self._pending_config = None
        self._publish(out)
        response.success = True
        response.message = f"end of data: {len(out.odometry)} last estimate(s) published; reset"
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------ parameters
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        names = {spec.name for spec in self._nav_specs}
        changed = {p.name: p.value for p in params if p.name in names}
        if not changed:
            return SetParametersResult(successful=True)
        values = current_values(self, self._nav_specs)
        values.update(changed)
        try:
            config = nav_config_from_params(values)
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self._pending_config = config
        self.get_logger().info(
            f"estimator parameter(s) {', '.join(sorted(changed))} changed: "
            "applied at the next ~/reset or ~/finish"
        )
        return SetParametersResult(successful=True)


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of ekf_node."""
    return run_node(EkfNode, NODE_NAME, args)
