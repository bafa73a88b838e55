"""ekf_node: the online estimator as a ROS 2 node.

Subscribes (relative names, remappable): ``imu/data`` (sensor_msgs/Imu), ``odom/wheel``
(nav_msgs/Odometry), ``imu/mag`` (sensor_msgs/MagneticField) with sensor-data QoS (best effort:
matches any publisher; with ``sensor_qos_reliable``, reliable: nothing is lost when the node
falls behind a replay, but a best-effort publisher is not heard: rclpy warns of the
incompatible QoS), and ``markers`` (sensor_msgs/NavSatFix, reliable, volatile: matches
reliable publishers, latched or not).

Publishes ``pipe_nav/odometry`` (nav_msgs/Odometry: pose of base_link in map with covariance,
twist in base_link), ``pipe_nav/datum`` (sensor_msgs/NavSatFix, latched: reliable + transient
local), ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, every ``diagnostics_period_s``) and,
with ``publish_tf``, the TF map -> base_link.

Services: ``~/reset`` (std_srvs/Trigger): restart the estimator (applying estimator parameters
changed since start); ``~/finish`` (std_srvs/Trigger): end of data: a last ``/diagnostics``
report (every input counted), flush the estimates still held for reordering, publish them,
then restart (used at the end of a bag replay).

All estimator settings are parameters (config/ekf.yaml); invalid values stop the node at start
with a message naming the parameter (exit status 2), and are refused when set at run time.

Start-up: the numeric kernels are loaded (about 1-2 s, from the prebuilt or installed module or
numba's cache) or compiled (the first run after an install the prebuilt ones do not fit:
minutes) by running the live filter over a short simulated run
(:func:`pipe_nav_core.warmup.warm_live`) BEFORE the subscriptions exist and "ready" is logged,
so that the first message is processed at once. Each input message is handled in its callback,
together with every message already waiting on the inputs, in stamp order; the estimates they
release are published there and then; ``/diagnostics`` reports the time that takes
(``latency_ms.*``) and each kind of input fault (``<input>.fault.<kind>``, see ekf_core).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, MagneticField, NavSatFix
from std_srvs.srv import Trigger
from tf2_ros import TransformBroadcaster

from pipe_nav_core import ConfigError, InputError, NavConfig, read_markers_csv, warm_live

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

NODE_NAME = "ekf_node"

MAX_TAKE = 20000  # messages taken from the queues in one callback at most

# Wall time (s) the kernels took to compile or load in this process; None until they did.
_KERNELS_READY_S: float | None = None


def warm_kernels(log: Callable[[str], None]) -> float:
    """Compile or load the numeric kernels once per process (log: one line before, one
    after, with the time taken); returns the seconds taken now (0 if already done)."""
    global _KERNELS_READY_S
    if _KERNELS_READY_S is not None:
        log(f"numeric kernels already loaded in this process ({_KERNELS_READY_S:.1f} s)")
        return 0.0
    log(
        "loading the numeric kernels (about a second; where no prebuilt or compiled ones "
        "fit this install, compiling them first takes minutes)"
    )
    taken = warm_live()
    _KERNELS_READY_S = taken
    log(f"numeric kernels ready in {taken:.1f} s")
    return taken


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
                survey = read_markers_csv(Path(s["survey_markers_csv"]).expanduser())
            except InputError as exc:  # the core's MarkerCsvError
                raise ConfigError(f"survey_markers_csv: {exc}") from None
        self._pending_config: NavConfig | None = None
        self.core = EkfCore(
            config,
            rclpy_types(),
            survey,
            map_frame=s["map_frame"],
            base_frame=s["base_frame"],
            imu_frame=s["imu_frame"],
            odom_frame=s["odom_frame"],
            max_stamp_lead_s=s["max_stamp_lead_s"],
            on_problem=self._on_problem,
        )
        # before any subscription: nothing arrives until the kernels are ready
        self.warmup_s = warm_kernels(self.get_logger().info)

        sensors = sensor_qos(s["sensor_qos_depth"], s["sensor_qos_reliable"])
        self._handlers = {
            "imu": self.core.on_imu,
            "odometer": self.core.on_odometer,
            "mag": self.core.on_mag,
            "markers": self.core.on_marker,
        }
        self._subs = {
            "imu": self.create_subscription(Imu, "imu/data", self._input("imu"), sensors),
            "odometer": self.create_subscription(
                Odometry, "odom/wheel", self._input("odometer"), sensors
            ),
            "mag": self.create_subscription(MagneticField, "imu/mag", self._input("mag"), sensors),
            "markers": self.create_subscription(
                NavSatFix, "markers", self._input("markers"), markers_subscription_qos()
            ),
        }

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

    # ------------------------------------------------------------------ input
    def _input(self, role: str) -> Callable[[Any, Any], None]:
        """The subscription callback of one input.

        It takes every message waiting on the four inputs along with this one and handles them
        in stamp order: behind a backlog the executor serves the subscriptions in turn, one
        message each, which lets the slower topics run ahead of the IMU by more than the
        reorder window (and the IMU samples would then be late). Each message goes to the core
        with its DDS source timestamp (s, for the burst check); the estimates it releases are
        published at once, and the time from the start of this callback to the end of that
        publishing is recorded for /diagnostics (``latency_ms.*``).
        """

        def callback(msg: Any, info: Any) -> None:
            start = time.perf_counter()
            batch = [(role, msg, info), *self._waiting()]
            if len(batch) > 1:
                batch.sort(key=_stamp_key)  # stable: a topic's own order is kept
            for r, m, i in batch:
                self._handle(r, m, i, start)

        return callback

    def _waiting(self) -> list[tuple[str, Any, Any]]:
        """Every message already waiting in the input subscriptions' queues (role, msg, info);
        empty where rclpy's take is not available."""
        out: list[tuple[str, Any, Any]] = []
        for role, sub in self._subs.items():
            try:
                with sub.handle:
                    while len(out) < MAX_TAKE:
                        taken = sub.handle.take_message(sub.msg_type, sub.raw)
                        if taken is None:
                            break
                        out.append((role, taken[0], taken[1]))
            except Exception:  # noqa: BLE001 - the executor delivers what is left
                continue
        return out

    def _handle(self, role: str, msg: Any, info: Any, start: float) -> None:
        source_ns = _source_timestamp_ns(info)
        self._handlers[role](msg, None if source_ns is None else source_ns * 1e-9)
        out = self.core.poll()
        if out.odometry or out.datum is not None:
            self._publish(out)
        if out.odometry:
            done_ns = time.time_ns()
            self.core.latency.add(
                time.perf_counter() - start,
                None if source_ns is None else (done_ns - source_ns) * 1e-9,
                len(out.odometry),
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
        self._publish_diagnostics()  # the counts at the end of data, before the reset
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


def _stamp_key(item: tuple[str, Any, Any]) -> tuple[int, int]:
    """Sort key of a (role, message, info): the header stamp (sec, nanosec)."""
    try:
        stamp = item[1].header.stamp
        return int(stamp.sec), int(stamp.nanosec)
    except (AttributeError, TypeError, ValueError):
        return (2**62, 0)


def _source_timestamp_ns(info: Any) -> int | None:
    """The publisher's source timestamp (ns, its system clock) of an rclpy MessageInfo, or None
    when the middleware gives none."""
    try:
        ns = int(info["source_timestamp"])
    except (KeyError, TypeError, ValueError):
        return None
    return ns if ns > 0 else None


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of ekf_node."""
    return run_node(EkfNode, NODE_NAME, args)
