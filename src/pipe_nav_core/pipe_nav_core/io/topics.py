"""Topic names, message type names, the bag error and the read report (see INTERFACES.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pipe_nav_core.types import Marker

IMU_TYPE = "sensor_msgs/msg/Imu"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
MAG_TYPE = "sensor_msgs/msg/MagneticField"
NAVSATFIX_TYPE = "sensor_msgs/msg/NavSatFix"
PATH_TYPE = "nav_msgs/msg/Path"
POSE_ARRAY_TYPE = "geometry_msgs/msg/PoseArray"
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"

OUTPUT_PATH_TOPIC = "/pipe_nav/path"
OUTPUT_DATUM_TOPIC = "/pipe_nav/datum"
OUTPUT_ODOMETRY_TOPIC = "/pipe_nav/odometry"
OUTPUT_BENDS_TOPIC = "/pipe_nav/bends"  # bend apexes (geometry_msgs/PoseArray, map)
DIAGNOSTICS_TOPIC = "/diagnostics"

# Reasons a message can be skipped while reading (keys of BagReport.skipped).
SKIP_NAN = "nan"  # a value (or the stamp) is NaN or infinite
SKIP_BAD_CDR = "bad_cdr"  # payload could not be deserialized
SKIP_NON_MONOTONIC = "non_monotonic"  # stamp more than the reorder window behind the newest one
SKIP_DUPLICATE = "duplicate"  # same stamp as an earlier sample of the topic
SKIP_TIME_JUMP = "time_jump"  # isolated stamp far ahead of its neighbours (clock glitch)
SKIP_LATE = "late"  # streaming only: arrived after its time chunk was already handed out
SKIP_UNKNOWN_TYPE = "unknown_type"  # the topic carries an unexpected message type or encoding
SKIP_CORRUPT_CHUNK = "corrupt_chunk"  # the MCAP chunk holding it failed to decompress or its CRC


@dataclass(frozen=True)
class TopicNames:
    """Input topic names (INTERFACES.md). Override to read bags recorded under other names."""

    imu: str = "/imu/data"
    odometer: str = "/odom/wheel"
    mag: str = "/imu/mag"
    markers: str = "/markers"

    def roles(self) -> dict[str, str]:
        """Map topic name -> role ('imu', 'odometer', 'mag', 'markers')."""
        return {
            self.imu: "imu",
            self.odometer: "odometer",
            self.mag: "mag",
            self.markers: "markers",
        }


DEFAULT_TOPICS = TopicNames()

ROLE_TYPES = {
    "imu": IMU_TYPE,
    "odometer": ODOMETRY_TYPE,
    "mag": MAG_TYPE,
    "markers": NAVSATFIX_TYPE,
}


def normalize_type(name: str) -> str:
    """'sensor_msgs/Imu' or 'sensor_msgs/msg/Imu' -> 'sensor_msgs/msg/Imu'."""
    parts = name.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name.strip()


@dataclass
class BagReport:
    """What reading a bag found.

    counts: accepted samples per topic name (after every check).
    skipped: number of dropped messages per reason (see the ``SKIP_*`` constants), all topics.
    skipped_by_topic: the same per topic name: {topic: {reason: count}}.
    types: message type per topic name as recorded in the bag (all topics, not only ours).
    truncated: the file (or one of the files) ended early or had unreadable parts; what could
    be read was used.
    warnings: one-line human-readable messages.
    files: the MCAP files read, in order.
    imu_noise_declared: the per-sample variance diagonals ((rad/s)^2, (m/s^2)^2) the first
    Imu message declares ({"gyro_variance": [3], "accel_variance": [3]}), or {}.
    markers_outside: the markers left out because their passage lies outside the data (a
    marker clock offset is measured on them too: faults.marker_clock).
    """

    path: str = ""
    counts: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    skipped_by_topic: dict[str, dict[str, int]] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    truncated: bool = False
    warnings: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    imu_noise_declared: dict[str, list[float]] = field(default_factory=dict)
    markers_outside: list[Marker] = field(default_factory=list)

    def add_skipped(self, topic: str, reason: str, n: int = 1) -> None:
        """Count n messages of ``topic`` dropped for ``reason``."""
        if n <= 0:
            return
        self.skipped[reason] = self.skipped.get(reason, 0) + int(n)
        per = self.skipped_by_topic.setdefault(topic, {})
        per[reason] = per.get(reason, 0) + int(n)

    def warn(self, message: str) -> None:
        """Add a warning line (duplicates are ignored)."""
        if message not in self.warnings:
            self.warnings.append(message)

    @property
    def total_skipped(self) -> int:
        """All dropped messages."""
        return sum(self.skipped.values())

    def summary(self) -> str:
        """A few human-readable lines: counts, skips, truncation, warnings."""
        lines = [f"{self.path}: " + ", ".join(f"{t} {n}" for t, n in self.counts.items())]
        for topic, reasons in self.skipped_by_topic.items():
            lines.append(
                f"  skipped on {topic}: " + ", ".join(f"{r} {n}" for r, n in reasons.items())
            )
        if self.truncated:
            lines.append("  bag is truncated or partly unreadable")
        lines.extend(f"  warning: {w}" for w in self.warnings)
        return "\n".join(lines)
