"""The three sensor driver nodes: imu_driver_node, odometer_driver_node, magnetometer_driver_node.

Each reads one sensor from its ``source`` (serial line protocol, recorder CSV log, or the
simulator) and publishes it with sensor-data QoS (best effort, volatile):

- imu_driver_node: sensor_msgs/Imu on ``imu/data`` (frame imu_link, SI units, mean over the
  sample interval; the mount rotation is applied by ekf_node, not here);
- odometer_driver_node: nav_msgs/Odometry on ``odom/wheel`` (distance from counts, speed over a
  window); in log and sim mode also the marker passages, sensor_msgs/NavSatFix on ``markers``
  (reliable, transient local);
- magnetometer_driver_node: sensor_msgs/MagneticField on ``imu/mag`` (tesla, hard/soft iron
  corrected).

Decoding, calibration and message contents live in the rclpy-free ``sources`` and
``driver_core`` modules; this module is threads and publishers around them.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import math
import os
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, MagneticField, NavSatFix

from pipe_nav_core import ConfigError, InputError, read_markers_csv

from .driver_core import MARKER, DriverCore
from .msg_types import rclpy_types
from .params import DRIVER_NODE_NAMES, driver_param_specs, driver_settings_from_params
from .ros_common import PipeNavNode, declare, latched_qos, run_node, sensor_qos
from .sources import (
    DeviceClockSync,
    LineAssembler,
    ProtocolError,
    ReadStats,
    Sample,
    Timeline,
    log_samples,
    merge_by_time,
    parse_line,
    play,
    sim_samples,
)

TOPICS = {"imu": "imu/data", "odometer": "odom/wheel", "mag": "imu/mag"}
MESSAGE_TYPES = {"imu": Imu, "odometer": Odometry, "mag": MagneticField}
MARKERS_TOPIC = "markers"


class SensorDriverNode(PipeNavNode):
    """One driver node (kind: imu | odometer | mag); kwargs go to rclpy.node.Node (for example
    ``parameter_overrides``). Raises ConfigError on invalid parameters or an unusable source."""

    def __init__(self, kind: str, **kwargs: Any) -> None:
        super().__init__(DRIVER_NODE_NAMES[kind], **kwargs)
        self.kind = kind
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._port: Any = None
        values = declare(self, driver_param_specs(kind), read_only=True)
        self.settings = driver_settings_from_params(kind, values)
        self.core = DriverCore(self.settings, rclpy_types())
        self.stats = ReadStats()
        s = self.settings
        self.publisher = self.create_publisher(MESSAGE_TYPES[kind], TOPICS[kind], sensor_qos(50))
        self.marker_publisher = None
        if kind == "odometer" and s["source"] != "serial" and s["publish_markers"]:
            self.marker_publisher = self.create_publisher(
                NavSatFix, MARKERS_TOPIC, latched_qos(1000)
            )
        if s["source"] == "serial":
            self._open_serial()
            target = self._read_serial
        else:
            samples, timeline = self._replay_source()
            target = functools.partial(self._replay, samples, timeline)
        self._thread = threading.Thread(target=target, name=f"{kind}_source", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ output
    def _emit(self, sample: Sample, stamp: float) -> None:
        for role, msg in self.core.messages(sample, stamp):
            if role == MARKER:
                if self.marker_publisher is not None:
                    self.marker_publisher.publish(msg)
            else:
                self.publisher.publish(msg)

    def _bad_input(self, where: str, reason: str) -> None:
        self.get_logger().warning(f"skipped {where}: {reason}", throttle_duration_sec=5.0)

    # ------------------------------------------------------------------ log and sim
    def _replay_source(self) -> tuple[Iterator[Sample], Timeline]:
        s = self.settings
        markers: list[Any] = []
        if s["source"] == "log":
            stream: Iterator[Sample] = log_samples(
                s["log_file"],
                self.kind,
                self.core.scales,
                self.stats,
                on_error=lambda n, why: self._bad_input(f"{s['log_file']} line {n}", why),
            )
            first = next(stream, None)  # checks the file and its header now, at start-up
            if first is None:
                raise ConfigError(f"log_file {s['log_file']!r} holds no {self.kind} samples")
            stream = itertools.chain([first], stream)
            # the log's first sample is due at start_time; marker passages do not move it (a
            # marker before the log would delay this log against the other drivers' logs):
            # one logged earlier is published at once, stamped with its own time.
            t_ref = first.t
            if self.kind == "odometer" and s["markers_csv"] and s["publish_markers"]:
                try:
                    markers = read_markers_csv(Path(s["markers_csv"]).expanduser())
                except InputError as exc:  # the core's MarkerCsvError
                    raise ConfigError(f"markers_csv: {exc}") from None
                timed = [m for m in markers if math.isfinite(m.t)]
                if len(timed) < len(markers):  # survey rows without a passage time
                    self.get_logger().info(
                        f"markers_csv: {len(markers) - len(timed)} marker(s) without time_s "
                        "not published (survey only: give them to ekf_node's survey_markers_csv)"
                    )
                markers = timed
        else:
            samples, t_ref = sim_samples(self.kind, s["scenario"], s["seed"])
            stream = iter(samples)
        if markers:
            stream = merge_by_time(stream, markers)
        start = s["start_time"] if s["start_time"] > 0 else time.time() + 1.0
        timeline = Timeline(
            t_ref=t_ref, start=start, rate=s["rate"], restamp=s["stamps"] == "clock"
        )
        self.get_logger().info(
            f"{s['source']} source ready; first sample due at {start:.3f} (system time), "
            f"rate x{s['rate']:g}, stamps {s['stamps']}"
        )
        late = time.time() - start
        if late > 0.5:  # the samples due meanwhile go out in one burst
            self.get_logger().warning(
                f"source ready {late:.1f} s after start_time: the first {late * s['rate']:.1f} s "
                "of data go out at once (subscribers may drop some); give a later start_time "
                "(live.launch.py: a longer startup_delay)"
            )
        return stream, timeline

    def _replay(self, samples: Iterator[Sample], timeline: Timeline) -> None:
        try:
            count = play(samples, timeline, self._emit, self._stop.wait)
        except ConfigError as exc:
            self.get_logger().error(str(exc))
            self.exit_code = 2
            return
        except Exception as exc:  # noqa: BLE001 - report and stop this node, not the process
            if self._stop.is_set() or not self.context.ok():
                return  # shut down (Ctrl-C, launch ending) while a sample was being published
            self.get_logger().error(f"source failed: {type(exc).__name__}: {exc}")
            self.exit_code = 1
            return
        if self._stop.is_set():
            return
        published = self.core.published
        markers = f" and {count - published} markers" if count > published else ""
        self.get_logger().info(
            f"source exhausted after {published} samples{markers} "
            f"(skipped: {self.stats.malformed} malformed, {self.stats.non_increasing} out of order)"
        )
        if self.settings["exit_when_done"]:
            self.exit_code = 0

    # ------------------------------------------------------------------ serial
    def _open_serial(self) -> None:
        s = self.settings
        try:
            import serial  # pyserial, imported only for this source
        except ImportError:
            raise ConfigError(
                "source 'serial' needs pyserial: sudo apt install python3-serial "
                "(or pip install pyserial)"
            ) from None
        try:
            self._port = serial.Serial(s["port"], baudrate=s["baud"], timeout=0.2)
        except (serial.SerialException, ValueError, OSError) as exc:
            errno = getattr(exc, "errno", None)
            reason = os.strerror(errno) if isinstance(errno, int) else str(exc)
            if errno == 13:  # EACCES
                reason += " (on Linux: add the user to the dialout group)"
            raise ConfigError(
                f"cannot open serial port {s['port']!r} at {s['baud']} baud: {reason}"
            ) from None
        self._serial_error = serial.SerialException
        self.get_logger().info(f"reading {s['port']} at {s['baud']} baud, stamps {s['stamps']}")

    def _read_serial(self) -> None:
        s = self.settings
        lines = LineAssembler()
        sync = DeviceClockSync()
        mode = s["stamps"]
        port = self._port
        while not self._stop.is_set():
            try:
                data = port.read(max(1, port.in_waiting))
            except (self._serial_error, OSError) as exc:
                if not self._stop.is_set():
                    self.get_logger().error(f"serial port {s['port']} failed: {exc}")
                    self.exit_code = 1
                return
            if not data:
                continue
            arrival = self.get_clock().now().nanoseconds * 1e-9
            overlong = lines.overlong
            complete = lines.feed(data)
            if lines.overlong > overlong:  # garbage or a wrong baud rate
                self.stats.malformed += lines.overlong - overlong
                self._bad_input("serial data", f"line longer than {lines.max_length} bytes")
            for line in complete:
                self.stats.lines += 1
                try:
                    sample = parse_line(line, self.kind, self.core.scales)
                except ProtocolError as exc:
                    self.stats.malformed += 1
                    self._bad_input("serial line", str(exc))
                    continue
                if sample is None:
                    continue
                self.stats.samples += 1
                if mode == "synced":
                    stamp = sync.stamp(sample.t, arrival)
                elif mode == "source":
                    stamp = sample.t
                else:  # clock: arrival time
                    stamp = arrival
                self._emit(sample, stamp)

    # ------------------------------------------------------------------ shutdown
    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        if self._port is not None:
            with contextlib.suppress(Exception):  # closing a failed port may fail again
                self._port.close()


def _main(kind: str, args: Sequence[str] | None) -> int:
    return run_node(lambda: SensorDriverNode(kind), DRIVER_NODE_NAMES[kind], args)


def main_imu(args: Sequence[str] | None = None) -> int:
    """Entry point of imu_driver_node."""
    return _main("imu", args)


def main_odometer(args: Sequence[str] | None = None) -> int:
    """Entry point of odometer_driver_node."""
    return _main("odometer", args)


def main_magnetometer(args: Sequence[str] | None = None) -> int:
    """Entry point of magnetometer_driver_node."""
    return _main("mag", args)
