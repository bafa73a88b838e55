"""The message handling of ekf_node, without rclpy.

:class:`EkfCore` takes already-deserialized input messages (rclpy's or rosbags' classes alike),
feeds the :class:`~pipe_nav_core.engine.Navigator` (which orders the samples by stamp across
topics), and turns its estimates into nav_msgs/Odometry, the datum into sensor_msgs/NavSatFix
and its counters into diagnostic_msgs/DiagnosticArray, built with the given message classes.
The node is parameters, subscriptions, timers and publishers around one EkfCore, so the same
code path runs here under test with rosbags' classes, in ekf_node, and in ``pipe-nav replay``.

A malformed message (missing fields, wrong array sizes, values that do not convert) is counted
per topic and skipped; NaN and infinite samples are counted and dropped by the engine. Nothing a
message contains can stop the node.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pipe_nav_core.config import NavConfig
from pipe_nav_core.engine import NavEstimate, Navigator
from pipe_nav_core.io import rosmsg
from pipe_nav_core.types import Datum, Marker

from pipe_nav_core import attitude as att

# Topic role -> topic name (INTERFACES.md), for dispatching the messages of a bag by topic.
INPUT_TOPICS = {
    "imu": "/imu/data",
    "odometer": "/odom/wheel",
    "mag": "/imu/mag",
    "markers": "/markers",
}

OK, WARN, ERROR = 0, 1, 2
DIAGNOSTIC_NAME = "pipe_nav: ekf_node"
HARDWARE_ID = "pipe_nav"

# Exceptions a malformed message raises while it is converted.
_MALFORMED = (ValueError, TypeError, AttributeError, IndexError, KeyError, OverflowError)


@dataclass
class TopicCounters:
    """Per input topic: messages received, malformed (skipped), refused by the engine."""

    received: int = 0
    malformed: int = 0
    refused: int = 0
    last_problem: str = ""


@dataclass
class EkfOutput:
    """What one poll produced: the estimates, their Odometry messages (only once the datum is
    known; estimates before are counted, not published) and a datum NavSatFix when the datum
    became known or changed (publish it latched)."""

    estimates: list[NavEstimate] = field(default_factory=list)
    odometry: list[Any] = field(default_factory=list)
    datum: Any | None = None


def twist_covariance(est: NavEstimate, angular_variance: float) -> np.ndarray:
    """6x6 covariance of the twist in base_link: the ENU velocity covariance rotated into the
    body, and ``angular_variance`` (rad/s)^2 on the angular diagonal."""
    c_nb = att.dcm_from_quat(np.asarray(est.quat_nb, dtype=np.float64))
    cov = np.zeros((6, 6))
    cov[:3, :3] = c_nb.T @ np.asarray(est.cov_vel_n, dtype=np.float64) @ c_nb
    cov[3:, 3:] = np.eye(3) * angular_variance
    return cov


class EkfCore:
    """Input messages -> Navigator -> output messages (see the module docstring).

    config: estimator settings; types: message classes (rclpy_types() or rosbags');
    survey: surveyed markers known in advance; map_frame / base_frame: frame ids written into
    the Odometry messages; on_problem(role, text): told about each malformed message or engine
    refusal (for throttled logging).
    """

    def __init__(
        self,
        config: NavConfig,
        types: Any,
        survey: Sequence[Marker] = (),
        *,
        map_frame: str = "map",
        base_frame: str = "base_link",
        on_problem: Callable[[str, str], None] | None = None,
    ) -> None:
        self.types = types
        self.map_frame = map_frame
        self.base_frame = base_frame
        self.on_problem = on_problem
        self.counters = {role: TopicCounters() for role in INPUT_TOPICS}
        self.estimates_published = 0
        self.estimates_without_datum = 0
        self.poll_errors = 0
        self.resets = 0
        self.last_estimate: NavEstimate | None = None
        self._configure(config, survey)
        self._rate_mark: tuple[float, dict[str, int]] | None = None
        self._problem_mark = 0
        self._error_mark = 0

    def _configure(self, config: NavConfig, survey: Sequence[Marker]) -> None:
        self.config = config
        self.survey = list(survey)
        self.nav = Navigator(config, self.survey)
        self._datum_sent: Datum | None = None
        spec = config.imu_spec()
        # variance of the mean rate over one filter epoch: white noise plus bias instability
        self.angular_variance = (
            spec.gyro_arw**2 * config.filter_rate_hz + spec.gyro_bias_instability**2
        )

    # ------------------------------------------------------------------ input
    def on_imu(self, msg: Any) -> bool:
        """A sensor_msgs/Imu; True if it reached the engine."""
        return self._feed("imu", msg, rosmsg.imu_from_msg, self.nav.push_imu)

    def on_odometer(self, msg: Any) -> bool:
        """A nav_msgs/Odometry of the wheel odometer (/odom/wheel)."""
        return self._feed("odometer", msg, rosmsg.wheel_from_msg, self.nav.push_odometer)

    def on_mag(self, msg: Any) -> bool:
        """A sensor_msgs/MagneticField."""
        return self._feed("mag", msg, rosmsg.mag_from_msg, self.nav.push_mag)

    def on_marker(self, msg: Any) -> bool:
        """A sensor_msgs/NavSatFix marker passage."""
        return self._feed(
            "markers", msg, lambda m: (rosmsg.marker_from_msg(m),), self.nav.push_marker
        )

    def on_message(self, topic: str, msg: Any, topics: Mapping[str, str] = INPUT_TOPICS) -> bool:
        """Dispatch by topic name (``topics``: role -> name); other topics are ignored (False)."""
        handlers = {
            "imu": self.on_imu,
            "odometer": self.on_odometer,
            "mag": self.on_mag,
            "markers": self.on_marker,
        }
        for role, name in topics.items():
            if name == topic:
                return handlers[role](msg)
        return False

    def _feed(self, role: str, msg: Any, convert: Callable[[Any], tuple], push: Callable) -> bool:
        c = self.counters[role]
        c.received += 1
        try:
            args = convert(msg)
        except _MALFORMED as exc:
            c.malformed += 1
            self._problem(c, role, f"malformed message skipped: {type(exc).__name__}: {exc}")
            return False
        try:
            push(*args)
        except Exception as exc:  # noqa: BLE001 - a sample the engine refuses must not stop the node
            c.refused += 1
            self._problem(c, role, f"sample refused by the engine: {type(exc).__name__}: {exc}")
            return False
        return True

    def _problem(self, c: TopicCounters, role: str, text: str) -> None:
        c.last_problem = text
        if self.on_problem is not None:
            self.on_problem(role, text)

    # ------------------------------------------------------------------ output
    def poll(self) -> EkfOutput:
        """New estimates since the last poll, as messages."""
        return self._output(self._engine("poll", self.nav.poll))

    def finish(self, config: NavConfig | None = None) -> EkfOutput:
        """End of data: process everything still held for reordering, return the last
        estimates, and start afresh (the next message begins a new run; with ``config`` if
        given)."""
        out = self._output(self._engine("finish", self.nav.finish))
        self.reset(config=config)
        return out

    def _engine(self, what: str, call: Callable[[], list[NavEstimate]]) -> list[NavEstimate]:
        try:
            return call()
        except Exception as exc:  # noqa: BLE001 - keep the node alive, report on /diagnostics
            self.poll_errors += 1
            if self.on_problem is not None:
                self.on_problem("engine", f"{what} failed: {type(exc).__name__}: {exc}")
            return []

    def reset(
        self, config: NavConfig | None = None, survey: Sequence[Marker] | None = None
    ) -> None:
        """Back to waiting for the static alignment; with a new config or survey if given.

        The datum is published again once it is known again.
        """
        self.resets += 1
        self._configure(
            self.config if config is None else config,
            self.survey if survey is None else survey,
        )

    def _output(self, estimates: list[NavEstimate]) -> EkfOutput:
        out = EkfOutput(estimates=list(estimates))
        datum = self.nav.datum
        if datum is not None and datum != self._datum_sent:
            t = estimates[0].t if estimates else self._latest_stamp()
            out.datum = rosmsg.datum_to_msg(self.types, datum, t)
            self._datum_sent = datum
        for est in estimates:
            if datum is None:
                self.estimates_without_datum += 1
                continue
            out.odometry.append(self.odometry(est, datum))
        if estimates:
            self.last_estimate = estimates[-1]
        self.estimates_published += len(out.odometry)
        return out

    def odometry(self, est: NavEstimate, datum: Datum) -> Any:
        """nav_msgs/Odometry of one estimate: pose of base_link in map (ENU at the datum) with
        its covariance over [E, N, U, rotation about E, N, U]; twist in base_link."""
        msg = rosmsg.odometry_to_msg(
            self.types,
            est.t,
            datum,
            est.lat,
            est.lon,
            est.h,
            est.quat_nb,
            est.vel_n,
            est.omega_b,
            est.cov_pose,
            twist_covariance(est, self.angular_variance),
        )
        msg.header.frame_id = self.map_frame
        msg.child_frame_id = self.base_frame
        return msg

    def _latest_stamp(self) -> float:
        if self.last_estimate is not None:
            return self.last_estimate.t
        return 0.0

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self, stamp: float, now: float) -> Any:
        """diagnostic_msgs/DiagnosticArray of the node's health.

        stamp: header stamp, s (ROS clock); now: a monotonic time, s, for the input rates
        (computed between successive calls). Level: ERROR when the engine failed since the last
        call; WARN when messages were malformed or refused since the last call, an input that
        was flowing stopped, or the data do not fit the IMU noise model
        (Navigator.model_warnings: the configured imu_grade is likely wrong); else OK.
        """
        level, message, values = self.health(now)
        return rosmsg.diagnostics_to_msg(
            self.types, stamp, DIAGNOSTIC_NAME, level, message, values, hardware_id=HARDWARE_ID
        )

    def health(self, now: float) -> tuple[int, str, dict[str, int | float | str]]:
        """(level, one-line message, key/values) for the diagnostics (see :meth:`diagnostics`)."""
        received = {role: c.received for role, c in self.counters.items()}
        rates = {role: 0.0 for role in received}
        stopped: list[str] = []
        if self._rate_mark is not None:
            t0, before = self._rate_mark
            dt = now - t0
            if dt > 0:
                for role in received:
                    rates[role] = (received[role] - before[role]) / dt
            stopped = [r for r in ("imu", "odometer") if before[r] > 0 and received[r] == before[r]]
        self._rate_mark = (now, received)

        values: dict[str, int | float | str] = {}
        for role, c in self.counters.items():
            values[f"{role}.rate_hz"] = round(rates[role], 3)
            values[f"{role}.received"] = c.received
            values[f"{role}.malformed"] = c.malformed
            values[f"{role}.refused"] = c.refused
        values["estimates_published"] = self.estimates_published
        values["estimates_without_datum"] = self.estimates_without_datum
        values["datum_known"] = "yes" if self.nav.datum is not None else "no"
        values["resets"] = self.resets
        values["engine_errors"] = self.poll_errors
        for key, value in self.nav.diagnostics().items():
            values[f"engine.{key}"] = value

        problems = sum(c.malformed + c.refused for c in self.counters.values())
        new_problems = problems - self._problem_mark
        self._problem_mark = problems
        state = str(values.get("engine.state", "?"))
        summary = ", ".join(f"{r} {rates[r]:.1f} Hz" for r in ("imu", "odometer", "mag"))
        new_errors = self.poll_errors - self._error_mark
        self._error_mark = self.poll_errors
        if new_errors:
            level, message = ERROR, f"engine failed {new_errors} time(s) since the last report"
        elif new_problems:
            level, message = WARN, f"{new_problems} malformed or refused message(s); {summary}"
        elif stopped:
            level, message = WARN, f"no {' and no '.join(stopped)} data since the last report"
        elif misfit := self.nav.model_warnings():
            level, message = WARN, misfit[0]
        elif sum(received.values()) == 0:
            level, message = OK, "waiting for data"
        elif self.nav.datum is None:
            level, message = OK, f"{state}, waiting for the first marker (datum); {summary}"
        else:
            level, message = OK, f"{state}; {summary}"
        return level, message, values
