"""Shared helpers of the launch tests in this folder (run by launch_testing, not collected by
pytest; tests/integration/test_ros_launch.py runs each ``*_launch_test.py`` with
``python -m launch_testing.launch_test FILE``).

- :func:`launch_file`: the installed launch file, as ``ros2 launch pipe_nav_ros NAME`` finds it.
- :func:`work_dir`: where a test writes (``PIPE_NAV_LAUNCH_TMP``, set by the pytest wrapper to
  its tmp_path; else a new temporary directory).
- :func:`crop_sample_bag`: the first seconds of bags/sample.mcap as a new, shorter .mcap.
- :class:`Probe`: a node of its own (own rclpy context, spun in a thread) recording topics.
- :class:`HoldUntilTestsDone`: keeps the launch from finishing before the active tests have.
"""

from __future__ import annotations

import asyncio
import math
import os
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rclpy
from ament_index_python.packages import get_package_share_directory
from launch.action import Action
from launch.launch_context import LaunchContext
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

PACKAGE = "pipe_nav_ros"
ROOT = Path(__file__).resolve().parents[3]
SAMPLE_BAG = ROOT / "bags" / "sample.mcap"

# Subscriptions of the probe: best effort matches the drivers' and any publisher; reliable +
# transient local receives the latched topics even when it joins after their publication.
SENSOR = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=5000, reliability=ReliabilityPolicy.BEST_EFFORT
)
RELIABLE = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE
)
LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def launch_file(name: str) -> str:
    """Path of the installed launch file ``name`` of pipe_nav_ros (share/pipe_nav_ros/launch)."""
    return os.path.join(get_package_share_directory(PACKAGE), "launch", name)


def config_file(name: str) -> str:
    """Path of the installed parameter file ``name`` of pipe_nav_ros (share/pipe_nav_ros/config)."""
    return os.path.join(get_package_share_directory(PACKAGE), "config", name)


def work_dir(name: str) -> Path:
    """A new, empty directory for one launch test's files: ``$PIPE_NAV_LAUNCH_TMP/name`` when the
    pytest wrapper set that variable (its tmp_path), else a fresh temporary directory."""
    base = os.environ.get("PIPE_NAV_LAUNCH_TMP")
    if base:
        path = Path(base) / name
        path.mkdir(parents=True, exist_ok=False)
        return path
    return Path(tempfile.mkdtemp(prefix=f"pipe_nav_{name}_"))


def crop_sample_bag(out: Path, seconds: float) -> tuple[float, float, int]:
    """Write the first ``seconds`` (s) of bags/sample.mcap (every input topic) to ``out`` (.mcap).

    Returns (first, last) IMU header stamp of the crop in seconds, and its number of markers.
    """
    import math

    import numpy as np
    from pipe_nav_core.smooth.logs import slice_log  # a fixture's internal, not the API

    from pipe_nav_core import read_bag, write_sensor_bag

    log, _ = read_bag(SAMPLE_BAG)
    t_end = float(log.imu.t[0]) + seconds
    crop = slice_log(log, -math.inf, float(np.nextafter(t_end, math.inf)))  # t <= t_end
    write_sensor_bag(out, crop)
    return float(crop.imu.t[0]), float(crop.imu.t[-1]), len(crop.markers)


def stamp_s(msg: Any) -> float:
    """header.stamp of a message, s."""
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


class Probe:
    """A test node in a context of its own, spun on a background thread.

    ``record(topic, type, qos)`` returns a list that fills with (arrival time, message), the
    arrival time from time.time() (s since 1970, the clock the drivers' start_time is on).
    ``ROS_DOMAIN_ID`` is the process's (the wrapper's).
    """

    def __init__(self, name: str = "launch_test_probe") -> None:
        self.context = Context()
        # launch handles SIGINT in this process; rclpy must not take it over
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="probe_spin", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def record(self, topic: str, msg_type: Any, qos: QoSProfile) -> list[tuple[float, Any]]:
        received: list[tuple[float, Any]] = []
        self.node.create_subscription(
            msg_type, topic, lambda msg: received.append((time.time(), msg)), qos
        )
        return received

    def node_names(self) -> set[str]:
        return set(self.node.get_node_names())

    def publishers(self, topic: str) -> list[Any]:
        """rclpy TopicEndpointInfo of every publisher of ``topic`` (node name, QoS)."""
        return list(self.node.get_publishers_info_by_topic(topic))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def wait_until(condition: Callable[[], Any], timeout: float, period: float = 0.05) -> bool:
    """Poll ``condition`` until it is true or ``timeout`` (s) has passed; its last truth."""
    deadline = time.monotonic() + timeout
    while True:
        if condition():
            return True
        if time.monotonic() >= deadline:
            return bool(condition())
        time.sleep(period)


def median_step(values: list[float]) -> float:
    """Median of the differences of consecutive values (NaN for fewer than two)."""
    steps = sorted(b - a for a, b in zip(values, values[1:], strict=False))
    return steps[len(steps) // 2] if steps else math.nan


class HoldUntilTestsDone(Action):
    """Keeps the launch running until launch_testing's active tests have finished.

    launch_testing fails a run whose launch ends before its active tests do, and it shuts the
    launch down itself once they have. A launch file that ends by itself (a Shutdown action, as
    replay.launch.py and smooth.launch.py do when their work is done) would race the tests that
    watch it end. This action's future completes only when launch_testing's test thread
    (``test_runner_thread``) has finished, or after ``timeout`` (s); the launch's own shutdown
    still stops every process as it would, only the launch service waits for the tests.
    """

    TEST_THREAD = "test_runner_thread"

    def __init__(self, timeout: float = 600.0, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._timeout = timeout
        self._future: asyncio.Future[None] | None = None

    def execute(self, context: LaunchContext) -> None:
        self._future = context.asyncio_loop.create_task(self._hold())
        return None

    def get_asyncio_future(self) -> asyncio.Future[None] | None:
        return self._future

    async def _hold(self) -> None:
        deadline = time.monotonic() + self._timeout
        while time.monotonic() < deadline:
            runners = [t for t in threading.enumerate() if t.name == self.TEST_THREAD]
            if not any(t.is_alive() for t in runners):
                return
            await asyncio.sleep(0.1)
