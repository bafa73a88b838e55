"""smoother_node: smooth a recorded bag offline and publish the centreline.

Runs :func:`pipe_nav_core.app.pipeline.smooth_bag` on the parameter ``bag`` (as ``pipe-nav smooth``:
writes ``output`` and the optional csv / geojson / kml / plot files), reports progress in the
log and on ``/diagnostics``, then publishes ``pipe_nav/path`` (nav_msgs/Path in map),
``pipe_nav/datum`` (sensor_msgs/NavSatFix) and ``pipe_nav/bends`` (geometry_msgs/PoseArray in
map: one pose per bend at its apex, x along the pipe; empty without bends), all latched
(reliable + transient local: a subscriber that joins later still gets them). With
``exit_when_done`` the node exits after publishing (status 0; 1 when smoothing failed);
otherwise it stays up holding the latched path.
The estimator settings are the same parameters as ekf_node's (config/ekf.yaml).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from nav_msgs.msg import Path
from rclpy.clock import Clock, ClockType
from sensor_msgs.msg import NavSatFix

from .msg_types import rclpy_types
from .params import (
    SMOOTHER_NODE_SPECS,
    nav_config_from_params,
    nav_param_specs,
    smoother_node_settings,
)
from .ros_common import PipeNavNode, declare, latched_qos, run_node
from .smoother_core import DONE, FAILED, RUNNING, SmootherJob

NODE_NAME = "smoother_node"
LINGER_S = 1.0  # with exit_when_done: time left to deliver the latched messages before exiting
PROGRESS_LOG_S = 10.0  # an unchanged progress message is logged again after this long


class SmootherNode(PipeNavNode):
    """The smoother_node (see the module docstring); kwargs go to rclpy.node.Node. Raises
    ConfigError for invalid parameters (including a missing input bag)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        config = nav_config_from_params(declare(self, nav_param_specs(), read_only=True))
        self.settings = smoother_node_settings(declare(self, SMOOTHER_NODE_SPECS, read_only=True))
        self.path_pub = self.create_publisher(Path, "pipe_nav/path", latched_qos(1))
        self.datum_pub = self.create_publisher(NavSatFix, "pipe_nav/datum", latched_qos(1))
        self.bends_pub = self.create_publisher(PoseArray, "pipe_nav/bends", latched_qos(1))
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.job = SmootherJob(self.settings, config, rclpy_types())
        self._published_at: float | None = None
        self._logged = ("", 0.0)  # last progress message logged, and when
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(0.1, self._check, clock=steady)
        self.create_timer(self.settings["diagnostics_period_s"], self._report, clock=steady)
        self.get_logger().info(
            f"smoothing {self.settings['bag']} -> {self.settings['output']} "
            f"(method {self.settings['method']})"
        )
        self.job.start()

    def _check(self) -> None:
        job = self.job
        if job.state == FAILED and self.exit_code is None:
            self.get_logger().error(job.health()[1])
            self._report()
            self.exit_code = 1
        elif job.state == DONE and self._published_at is None:
            path, datum = job.messages()
            bends = job.bends_message()
            self.path_pub.publish(path)
            self.datum_pub.publish(datum)
            self.bends_pub.publish(bends)
            self._published_at = time.monotonic()
            for warning in job.warnings:
                self.get_logger().warning(f"bag: {warning}")
            self.get_logger().info(job.health()[1])
            self.get_logger().info(
                f"published {len(path.poses)} poses on pipe_nav/path and {len(bends.poses)} bend "
                "apexes on pipe_nav/bends (latched)"
            )
            self._report()
        elif (
            self._published_at is not None
            and self.settings["exit_when_done"]
            and time.monotonic() - self._published_at >= LINGER_S
        ):
            self.exit_code = 0

    def _report(self) -> None:
        if self.job.state == RUNNING:
            message = self.job.health()[1]
            now = time.monotonic()
            # log a new stage at once, the same one again every PROGRESS_LOG_S
            if message != self._logged[0] or now - self._logged[1] >= PROGRESS_LOG_S:
                self.get_logger().info(message)
                self._logged = (message, now)
        stamp = self.get_clock().now().nanoseconds * 1e-9
        self.diagnostics_pub.publish(self.job.diagnostics(stamp))


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of smoother_node."""
    return run_node(SmootherNode, NODE_NAME, args)
