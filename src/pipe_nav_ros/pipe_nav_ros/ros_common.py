"""rclpy helpers shared by the nodes: QoS profiles, parameter declaration, the main loop."""

from __future__ import annotations

import signal
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from pipe_nav_core import ConfigError, small_pages

from .params import ParamSpec


def sensor_qos(depth: int, reliable: bool = False) -> QoSProfile:
    """Sensor-data QoS (best effort, volatile) with a deeper history than the stock profile's 5,
    so a 1 kHz IMU survives a slow callback. A best-effort subscription matches reliable and
    best-effort publishers alike (drivers, ``ros2 bag play``), but loses what arrives while the
    node's process stands still for longer than its socket holds (measured at ten times real
    time: a 0.3 s stop lost nothing, a 1 s stop seconds of data). reliable: a reliable
    subscription instead, which loses nothing (the publisher waits) but matches only reliable
    publishers (a replay: replay.launch.py)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else qos_profile_sensor_data.reliability,
        durability=qos_profile_sensor_data.durability,
    )


def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable + transient local: late-joining subscribers get the last ``depth`` messages."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def markers_subscription_qos() -> QoSProfile:
    """Reliable + volatile, deep: matches a reliable publisher whether it is volatile or
    transient local (the odometer driver, ``ros2 bag play`` of a recorded /markers)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=100,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def declare(node: Node, specs: Sequence[ParamSpec], read_only: bool = False) -> dict[str, Any]:
    """Declare the parameters of ``specs`` on ``node`` and return their values (None = unset).

    Parameters are declared with dynamic typing: the values are checked and converted by
    :mod:`pipe_nav_ros.params` (which accepts ``10`` for a double, and names the parameter in
    its error), not by rclpy's static typing which would refuse the node with a type error.
    A spec's range is declared for tools and later changes; a value outside it at the start is
    declared without it, so that the node is refused with the params module's clear message.
    """
    values: dict[str, Any] = {}
    for spec in specs:
        descriptor = ParameterDescriptor(
            description=spec.description, dynamic_typing=True, read_only=read_only
        )
        if spec.range:
            low, high = spec.range
            descriptor.floating_point_range = [FloatingPointRange(from_value=low, to_value=high)]
        try:
            param = node.declare_parameter(spec.name, spec.default, descriptor)
        except InvalidParameterValueException:
            descriptor.floating_point_range = []
            param = node.declare_parameter(spec.name, spec.default, descriptor)
        values[spec.name] = param.value
    return values


def current_values(node: Node, specs: Sequence[ParamSpec]) -> dict[str, Any]:
    """The current values of already declared parameters (None = unset)."""
    return {spec.name: node.get_parameter(spec.name).value for spec in specs}


class PipeNavNode(Node):
    """A node the main loop can ask to stop: set ``exit_code`` to end :func:`run_node`."""

    exit_code: int | None = None

    def close(self) -> None:
        """Release resources (threads, ports) before the node is destroyed."""


class _CtrlC:
    """The Python side of SIGINT for :func:`run_node`.

    rclpy's own handler shuts the context down and then calls this one. While the node is
    being built (kernel loading can take minutes on a fresh install) the first Ctrl-C raises
    KeyboardInterrupt so the build stops at once; once it spins, Ctrl-C only records the stop,
    which the loop sees. Every later Ctrl-C is ignored: ``ros2 launch`` delivers it twice, and
    a KeyboardInterrupt landing in the clean-up would be a traceback instead of a stop.
    """

    def __init__(self) -> None:
        self.requested = False
        self.building = True

    def __call__(self, signum: int, frame: object) -> None:
        first = not self.requested
        self.requested = True
        if first and self.building:
            raise KeyboardInterrupt


def run_node(
    factory: Callable[[], PipeNavNode], name: str, args: Sequence[str] | None = None
) -> int:
    """Init rclpy, build the node, spin until shutdown or ``node.exit_code``; the exit status.

    A ConfigError raised while building the node (an invalid parameter) is logged as an error
    and gives exit status 2, so ``ros2 run`` and launch show a clear message and a failure.
    Ctrl-C is an ordinary stop (status 0, no traceback) wherever it lands, however often it
    comes (:class:`_CtrlC`); rclpy shuts the context down while a callback may still be
    converting a message, which makes that ``spin_once`` raise: once rclpy is shut down such
    an error is the stop, not a crash.
    """
    small_pages()  # no stalls on huge-page compaction (the smoother's arrays)
    ctrl_c = _CtrlC()
    signal.signal(signal.SIGINT, ctrl_c)  # before init: rclpy's handler chains to this one
    rclpy.init(args=list(args) if args is not None else None)
    node: PipeNavNode | None = None
    executor: SingleThreadedExecutor | None = None
    try:
        try:
            node = factory()
        except ConfigError as exc:
            get_logger(name).error(f"invalid parameters, not starting: {exc}")
            return 2
        ctrl_c.building = False
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok() and node.exit_code is None and not ctrl_c.requested:
            try:
                executor.spin_once(timeout_sec=0.2)
            except Exception:
                if rclpy.ok() and not ctrl_c.requested:
                    raise
                break  # shut down mid-callback by Ctrl-C
        return node.exit_code or 0
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        ctrl_c.building = False
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
