"""The message handling of ekf_node, without rclpy.

:class:`EkfCore` takes already-deserialized input messages (rclpy's or rosbags' classes alike),
feeds the :class:`~pipe_nav_core.filter.navigator.Navigator` (which orders the samples by stamp
across topics), and turns its estimates into nav_msgs/Odometry, the datum into sensor_msgs/NavSatFix
and its counters into diagnostic_msgs/DiagnosticArray, built with the given message classes.
The node is parameters, subscriptions, timers and publishers around one EkfCore, so the same
code path runs here under test with rosbags' classes, in ekf_node, and in ``pipe-nav replay``.

Every message is inspected before it reaches the engine, and each kind of fault is counted per
input under a stable name (``FAULT_KINDS``; in /diagnostics ``<input>.fault.<kind>``):

- ``nan``: a NaN or infinite value; the sample goes to the engine, which counts and drops it.
- ``frame_id``: a frame the input does not accept (INTERFACES.md): ``imu/data`` and ``imu/mag``
  ``imu_frame`` (imu_link), ``odom/wheel`` ``odom_frame`` (odom) with child ``base_frame``
  (base_link), each also with a tf prefix (``pig1/imu_link``); ``markers`` any non-empty name.
  The sample is dropped (its vectors are in an unknown frame).
- ``stamp_future``: a stamp more than ``max_stamp_lead_s`` ahead of the newest IMU, odometer or
  magnetometer stamp accepted so far. Dropped, so that it cannot move the engine's reorder
  buffer ahead and make every later sample late; but ``JUMP_CONFIRM`` consecutive such samples
  that agree with one another are a real jump of the data's clock (a gap, a restarted source):
  they are then used, from the first. A marker ahead of the data is held until the data reach
  its stamp (a survey published in advance); it is no fault when it was sent over
  ``BACKLOG_SENT_S`` after the newest data sample taken (``sent``, the sender's timestamps):
  then the data are behind in their delivery (a backlog after a stall), not the marker ahead.
- ``stamp_past``: a stamp not after the previous one of the same sensor, or older than what the
  engine already processed (its reorder horizon): dropped. ``JUMP_CONFIRM`` consecutive samples
  that agree with one another and lie over ``max_stamp_lead_s`` behind the data and behind their
  own input's previous stamp are a clock that went back (a bag played again): the estimator
  restarts on them (counted in ``resets``). A sample after its input's previous one but behind
  the data is that input's backlog (behind a stalled node each topic's backlog comes back at
  its own pace, the fastest one last): the engine waits for it while it arrives
  (filter.stream.MAX_BACKLOG_S), and one beyond that is dropped, never taken for a clock that
  went back.
- ``covariance``: a covariance array of the wrong size, not finite, or with a negative
  variance (the Imu ``-1`` "not provided" flag excepted). IMU, odometer and magnetometer
  covariances are not used (the noise model comes from ``imu_grade``): the sample is kept; a
  marker of the wrong size is dropped, one with unusable variances uses the default 0.05 m.
- ``burst``: messages sent faster than four times INTERFACES.md's highest rate of the input
  (IMU 1000 Hz, odometer 200 Hz, magnetometer 100 Hz), beyond a quarter of a second's worth of
  them (a token bucket on the sender's timestamps, ``sent``; the node passes each message's
  DDS source timestamp): counted, and used (nothing is wrong with their content). Without
  ``sent`` (offline) there is no burst check.

A malformed message (missing fields, values that do not convert) is counted per topic and
skipped. Nothing a message contains can stop the node.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipe_nav_core import (
    Datum,
    GuardedNavigator,
    Marker,
    NavConfig,
    NavEstimate,
    dcm_from_quat,
    rosmsg,
)

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

# Kinds of fault, named in /diagnostics as <input>.fault.<kind> (see the module docstring).
FAULT_KINDS = ("nan", "frame_id", "stamp_future", "stamp_past", "covariance", "burst")
STREAMS = ("imu", "odometer", "mag")  # the inputs whose stamps make the data's clock
MAX_RATE_HZ = {
    "imu": 1000.0,
    "odometer": 200.0,
    "mag": 100.0,
}  # INTERFACES.md, per input
BURST_FACTOR = 4.0  # messages sent faster than this times MAX_RATE_HZ ...
BURST_ALLOWANCE_S = 0.25  # ... beyond this many seconds' worth of them are a burst
JUMP_CONFIRM = 20  # consecutive agreeing samples off the data's clock that make a real jump
BACKLOG_SENT_S = 0.5  # s: a marker sent this long after the newest data sample taken: a backlog
DEFAULT_MAX_STAMP_LEAD_S = 1.0
MAX_HELD_MARKERS = 1000


@dataclass
class TopicCounters:
    """Per input topic: messages received, malformed (skipped), refused by the engine, and the
    faults found (kind -> count, FAULT_KINDS)."""

    received: int = 0
    malformed: int = 0
    refused: int = 0
    last_problem: str = ""
    faults: dict[str, int] = field(default_factory=lambda: dict.fromkeys(FAULT_KINDS, 0))


@dataclass
class Inspected:
    """One converted input message: its stamp (s), the engine call's arguments, whether its
    values are all finite, and its faults as (kind, text, drop)."""

    t: float
    args: tuple
    finite: bool
    faults: list[tuple[str, str, bool]] = field(default_factory=list)


class LatencyStats:
    """Processing latency of the published estimates since the last report (s).

    ``add(processing, from_source, n)``: one input message released ``n`` estimates;
    processing = wall time from the start of its callback to the return of the publishing of
    those estimates; from_source = from its publisher's source timestamp (the sender's system
    clock) to the same moment, or None when unknown.
    """

    def __init__(self) -> None:
        self.processing: list[float] = []
        self.from_source: list[float] = []

    def add(self, processing: float, from_source: float | None = None, n: int = 1) -> None:
        """Record one releasing message (see the class docstring)."""
        self.processing += [processing] * n
        if from_source is not None:
            self.from_source += [from_source] * n

    def report(self) -> dict[str, int | float]:
        """``latency_ms.median``/``.max``/``.estimates`` and ``latency_from_source_ms.median``/
        ``.max`` (ms; nan when nothing was published), then start afresh."""

        def stats(values: list[float]) -> tuple[float, float]:
            if not values:
                return math.nan, math.nan
            return round(statistics.median(values) * 1e3, 3), round(max(values) * 1e3, 3)

        med, top = stats(self.processing)
        smed, stop = stats(self.from_source)
        out: dict[str, int | float] = {
            "latency_ms.median": med,
            "latency_ms.max": top,
            "latency_ms.estimates": len(self.processing),
            "latency_from_source_ms.median": smed,
            "latency_from_source_ms.max": stop,
        }
        self.processing, self.from_source = [], []
        return out


def covariance_problem(values: Any, size: int, flag_ok: bool = False) -> str:
    """Why a covariance array is unusable ("" if it is fine): not ``size`` elements, not finite,
    or a negative variance on the diagonal. ``flag_ok``: element 0 may be -1 ("not provided",
    sensor_msgs/Imu)."""
    cov = np.asarray(values, dtype=np.float64).ravel()
    if cov.size != size:
        return f"has {cov.size} elements, not {size}"
    if flag_ok and cov[0] == -1.0:
        return ""
    # per message at 1 kHz: one reduction (finite iff the sum is, bar overflow) and indexing
    if not math.isfinite(float(cov.sum())) and not np.all(np.isfinite(cov)):
        return "is not finite"
    if not math.isfinite(float(cov.sum())):
        return "is too large"
    n = math.isqrt(size)
    if min(float(cov[k * (n + 1)]) for k in range(n)) < 0.0:
        return "has a negative variance"
    return ""


def declared_imu_noise(msg: Any) -> dict[str, list[float]] | None:
    """The per-sample variances an Imu message declares (covariance diagonals, (rad/s)^2 and
    (m/s^2)^2), for the engine's imu_grade auto; None when they are unknown (zero)."""
    gv = np.asarray(msg.angular_velocity_covariance, dtype=np.float64).reshape(-1)
    av = np.asarray(msg.linear_acceleration_covariance, dtype=np.float64).reshape(-1)
    if gv.size != 9 or av.size != 9:
        return None
    gd, ad = gv[[0, 4, 8]], av[[0, 4, 8]]
    if not (
        np.all(np.isfinite(gd)) and np.all(gd > 0) and np.all(np.isfinite(ad)) and np.all(ad > 0)
    ):
        return None
    return {"gyro_variance": gd.tolist(), "accel_variance": ad.tolist()}


def finite_estimate(est: NavEstimate) -> bool:
    """Whether every number an Odometry message carries of ``est`` is finite."""
    scalars = (est.t, est.lat, est.lon, est.h, est.distance)
    arrays = (est.vel_n, est.quat_nb, est.omega_b, est.cov_pose, est.cov_vel_n)
    return all(map(math.isfinite, scalars)) and all(bool(np.isfinite(a).all()) for a in arrays)


def frame_matches(frame_id: str, expected: str) -> bool:
    """frame_id is ``expected`` or ``<prefix>/expected`` (a tf prefix), leading "/" ignored."""
    f = str(frame_id).lstrip("/")
    return f == expected or f.endswith("/" + expected)


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
    c_nb = dcm_from_quat(np.asarray(est.quat_nb, dtype=np.float64))
    cov = np.zeros((6, 6))
    cov[:3, :3] = c_nb.T @ np.asarray(est.cov_vel_n, dtype=np.float64) @ c_nb
    cov[3:, 3:] = np.eye(3) * angular_variance
    return cov


class EkfCore:
    """Input messages -> Navigator -> output messages (see the module docstring).

    config: estimator settings; types: message classes (rclpy_types() or rosbags');
    survey: surveyed markers known in advance; map_frame / base_frame: frame ids written into
    the Odometry messages (base_frame is also the odometer's accepted child frame);
    imu_frame / odom_frame: the frame ids the IMU and magnetometer / the odometer accept;
    max_stamp_lead_s: how far (s) a stamp may lead the data's clock (stamp_future beyond);
    on_problem(role, text): told about each malformed message, fault or engine refusal (for
    throttled logging). The ``on_*`` handlers take the message and optionally ``sent``, the
    time its sender published it (s, the sender's clock; for the burst check).
    """

    def __init__(
        self,
        config: NavConfig,
        types: Any,
        survey: Sequence[Marker] = (),
        *,
        map_frame: str = "map",
        base_frame: str = "base_link",
        imu_frame: str = rosmsg.IMU_FRAME,
        odom_frame: str = rosmsg.ODOM_FRAME,
        max_stamp_lead_s: float = DEFAULT_MAX_STAMP_LEAD_S,
        on_problem: Callable[[str, str], None] | None = None,
    ) -> None:
        self.types = types
        self.map_frame = map_frame
        self.base_frame = base_frame
        self.imu_frame = imu_frame
        self.odom_frame = odom_frame
        self.max_stamp_lead_s = float(max_stamp_lead_s)
        self.on_problem = on_problem
        self.counters = {role: TopicCounters() for role in INPUT_TOPICS}
        self.latency = LatencyStats()
        self.estimates_published = 0
        self.estimates_without_datum = 0
        self.estimates_nonfinite = 0
        self.poll_errors = 0
        self.resets = 0
        self.last_estimate: NavEstimate | None = None
        # burst check: per stream, (tokens, last sent time)
        self._bucket: dict[str, tuple[float, float]] = {}
        self._configure(config, survey)
        self._rate_mark: tuple[float, dict[str, int]] | None = None
        self._problem_mark = 0
        self._fault_mark: dict[str, int] = {}
        self._error_mark = 0
        self._nonfinite_mark = 0

    def _configure(self, config: NavConfig, survey: Sequence[Marker]) -> None:
        self.config = config
        self.survey = list(survey)
        self.nav = GuardedNavigator(config, self.survey)
        self._datum_sent: Datum | None = None
        # the data's clock: newest accepted stamp of the streams, and per stream
        self.clock_s = -math.inf
        self._last_stamp = dict.fromkeys(STREAMS, -math.inf)
        # samples off the data's clock, held until JUMP_CONFIRM of them agree: (role, t, args)
        self._jump: list[tuple[str, float, tuple]] = []
        self._jump_sign = 0
        self._held_markers: list[Marker] = []  # ahead of the data, pushed when it reaches them
        self._data_sent = -math.inf  # s: the newest sent time of the data samples taken

    # ------------------------------------------------------------------ input
    def on_imu(self, msg: Any, sent: float | None = None) -> bool:
        """A sensor_msgs/Imu; True if it was accepted (passed to the engine, or a marker held
        until the data reach its stamp), False if it was dropped (counted)."""
        return self._feed("imu", msg, self._inspect_imu, self.nav.push_imu, sent)

    def on_odometer(self, msg: Any, sent: float | None = None) -> bool:
        """A nav_msgs/Odometry of the wheel odometer (/odom/wheel)."""
        return self._feed("odometer", msg, self._inspect_odometer, self.nav.push_odometer, sent)

    def on_mag(self, msg: Any, sent: float | None = None) -> bool:
        """A sensor_msgs/MagneticField."""
        return self._feed("mag", msg, self._inspect_mag, self.nav.push_mag, sent)

    def on_marker(self, msg: Any, sent: float | None = None) -> bool:
        """A sensor_msgs/NavSatFix marker passage."""
        return self._feed("markers", msg, self._inspect_marker, self.nav.push_marker, sent)

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

    # ---- conversion and inspection (frames, covariances, finiteness) of each input
    def _inspect_imu(self, msg: Any) -> Inspected:
        t, gyro, accel = rosmsg.imu_from_msg(msg)
        faults = self._frame_faults(msg.header.frame_id, self.imu_frame)
        for name, flag_ok in (
            ("orientation_covariance", True),
            ("angular_velocity_covariance", False),
            ("linear_acceleration_covariance", False),
        ):
            faults += self._covariance_faults(getattr(msg, name), name, 9, flag_ok)
        finite = math.isfinite(t) and bool(np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel)))
        if self.nav.declared_imu_noise is None and finite and not faults:
            self.nav.declared_imu_noise = declared_imu_noise(msg)
        return Inspected(t, (t, gyro, accel), finite, faults)

    def _inspect_odometer(self, msg: Any) -> Inspected:
        t, distance, speed = rosmsg.wheel_from_msg(msg)
        faults = self._frame_faults(msg.header.frame_id, self.odom_frame)
        faults += self._frame_faults(msg.child_frame_id, self.base_frame, "child_frame_id")
        faults += self._covariance_faults(msg.pose.covariance, "pose.covariance", 36)
        faults += self._covariance_faults(msg.twist.covariance, "twist.covariance", 36)
        finite = all(map(math.isfinite, (t, distance, speed)))
        return Inspected(t, (t, distance, speed), finite, faults)

    def _inspect_mag(self, msg: Any) -> Inspected:
        t, field_t = rosmsg.mag_from_msg(msg)
        faults = self._frame_faults(msg.header.frame_id, self.imu_frame)
        faults += self._covariance_faults(
            msg.magnetic_field_covariance, "magnetic_field_covariance", 9
        )
        finite = math.isfinite(t) and bool(np.all(np.isfinite(field_t)))
        return Inspected(t, (t, field_t), finite, faults)

    def _inspect_marker(self, msg: Any) -> Inspected:
        name = str(msg.header.frame_id)
        faults: list[tuple[str, str, bool]] = []
        if not name.strip():
            faults.append(("frame_id", "empty frame_id (the marker's name)", True))
        problem = covariance_problem(msg.position_covariance, 9)
        cov_type = int(msg.position_covariance_type)
        if np.asarray(msg.position_covariance).size != 9:  # the marker cannot be read
            faults.append(("covariance", f"position_covariance {problem}: dropped", True))
            return Inspected(rosmsg.stamp_to_sec(msg.header.stamp), (), False, faults)
        if problem and cov_type != rosmsg.COVARIANCE_TYPE_UNKNOWN:
            faults.append(("covariance", f"position_covariance {problem}: 0.05 m used", False))
        marker = rosmsg.marker_from_msg(msg)
        vals = (marker.t, marker.lat, marker.lon, marker.alt)
        return Inspected(marker.t, (marker,), all(map(math.isfinite, vals)), faults)

    @staticmethod
    def _frame_faults(
        frame_id: str, expected: str, what: str = "frame_id"
    ) -> list[tuple[str, str, bool]]:
        if frame_matches(frame_id, expected):
            return []
        return [("frame_id", f"{what} {str(frame_id)!r}, not {expected!r}: dropped", True)]

    @staticmethod
    def _covariance_faults(
        values: Any, name: str, size: int, flag_ok: bool = False
    ) -> list[tuple[str, str, bool]]:
        problem = covariance_problem(values, size, flag_ok)
        return [("covariance", f"{name} {problem} (not used)", False)] if problem else []

    # ---- the common path
    def _feed(
        self,
        role: str,
        msg: Any,
        inspect: Callable[[Any], Inspected],
        push: Callable,
        sent: float | None = None,
    ) -> bool:
        c = self.counters[role]
        c.received += 1
        if sent is not None and role in MAX_RATE_HZ:
            self._check_burst(role, c, sent)
        try:
            item = inspect(msg)
        except _MALFORMED as exc:
            c.malformed += 1
            self._problem(c, role, f"malformed message skipped: {type(exc).__name__}: {exc}")
            return False
        drop = False
        for kind in dict.fromkeys(kind for kind, _, _ in item.faults):  # each kind once
            c.faults[kind] += 1
        for kind, text, dropped in item.faults:
            drop |= dropped
            self._problem(c, role, f"{kind}: {text}")
        if drop:
            return False
        if not item.finite:
            # the engine counts and drops it (engine.dropped_nan_*) without touching its buffer
            c.faults["nan"] += 1
            self._problem(c, role, "nan: NaN or infinite value: dropped")
            return self._push(c, role, push, item.args)
        if role == "markers":
            return self._admit_marker(c, item.args[0], sent)
        ok = self._admit_sample(c, role, item.t, push, item.args)
        if ok and sent is not None and sent > self._data_sent:
            self._data_sent = sent
        return ok

    def _admit_sample(
        self, c: TopicCounters, role: str, t: float, push: Callable, args: tuple
    ) -> bool:
        """The stamp checks of an IMU, odometer or magnetometer sample (module docstring)."""
        ref, lead, horizon = self.clock_s, self.max_stamp_lead_s, self._horizon()
        if ref > -math.inf and t > ref + lead:
            return self._off_clock(c, role, t, args, 1)
        if ref > -math.inf and t < ref - lead and t <= horizon:
            if t > self._last_stamp[role]:  # its own stream goes on: a backlog, not a clock
                why = "a backlog longer than the engine waits for"
                return self._late(c, role, f"stamp {t:.6f} s, {t - ref:+.3f} s behind the other "
                                  f"inputs ({why})")  # fmt: skip
            return self._off_clock(c, role, t, args, -1)
        if t <= self._last_stamp[role] or t <= horizon:
            return self._late(c, role, f"stamp {t:.6f} s already passed (data at {ref:.6f} s)")
        self._jump.clear()
        return self._accept(c, role, t, push, args)

    def _late(self, c: TopicCounters, role: str, what: str) -> bool:
        """A sample too late to be used (what: its stamp and why): counted, named, dropped."""
        c.faults["stamp_past"] += 1
        self._problem(c, role, f"stamp_past: {what}: dropped")
        return False

    def _accept(self, c: TopicCounters, role: str, t: float, push: Callable, args: tuple) -> bool:
        self._last_stamp[role] = t
        if t > self.clock_s:
            self.clock_s = t
        ok = self._push(c, role, push, args)
        if self._held_markers and self._held_markers[0].t <= self.clock_s:
            self._release_markers()
        return ok

    def _off_clock(self, c: TopicCounters, role: str, t: float, args: tuple, sign: int) -> bool:
        """A sample over max_stamp_lead_s ahead of (sign 1) or behind (-1) the data's clock:
        a fault, held; JUMP_CONFIRM agreeing ones in a row are a real jump of the clock."""
        kind = "stamp_future" if sign > 0 else "stamp_past"
        c.faults[kind] += 1
        self._problem(
            c,
            role,
            f"{kind}: stamp {t:.6f} s, {t - self.clock_s:+.3f} s from the data: dropped",
        )
        held = self._jump
        if held and (sign != self._jump_sign or abs(t - held[-1][1]) > self.max_stamp_lead_s):
            held.clear()  # not the same new clock: start again from this sample
        self._jump_sign = sign
        held.append((role, t, args))
        if len(held) < JUMP_CONFIRM:
            return False
        jumped = t - self.clock_s
        items = list(held)
        if sign < 0:  # the clock went back: the estimator starts again on the new data
            self.reset()
            text = f"the data's clock went back by {-jumped:.3f} s: estimator restarted"
        else:
            text = f"the data's clock jumped ahead by {jumped:.3f} s: following it"
        self._jump = []
        self.clock_s = -math.inf
        self._last_stamp = dict.fromkeys(STREAMS, -math.inf)
        self._problem(c, role, text)
        pushes = {"imu": self.nav.push_imu, "odometer": self.nav.push_odometer,
                  "mag": self.nav.push_mag}  # fmt: skip
        ok = False
        for r, tr, a in items:  # the held samples in arrival order, this one last
            if tr > self._last_stamp[r] and tr > self._horizon():
                ok = self._accept(self.counters[r], r, tr, pushes[r], a)
        return ok

    def _admit_marker(self, c: TopicCounters, marker: Marker, sent: float | None = None) -> bool:
        """A marker ahead of the data's clock is held until the data reach it (a fault when it
        is over max_stamp_lead_s ahead and the data are not behind in their delivery: module
        docstring); one older than what the engine processed is dropped."""
        if self.clock_s == -math.inf or marker.t > self.clock_s:
            backlog = (
                sent is not None
                and self._data_sent > -math.inf
                and sent - self._data_sent > BACKLOG_SENT_S
            )
            if marker.t > self.clock_s + self.max_stamp_lead_s > -math.inf and not backlog:
                c.faults["stamp_future"] += 1
                self._problem(
                    c, "markers", f"stamp_future: marker {marker.name} at {marker.t:.3f} s is "
                    f"ahead of the data ({self.clock_s:.3f} s): held until the data reach it",
                )  # fmt: skip
                if len(self._held_markers) < MAX_HELD_MARKERS:
                    self._held_markers.append(marker)
                    self._held_markers.sort(key=lambda m: m.t)
                return False
            if len(self._held_markers) < MAX_HELD_MARKERS:
                self._held_markers.append(marker)
                self._held_markers.sort(key=lambda m: m.t)
            return True
        if marker.t <= self._horizon():
            c.faults["stamp_past"] += 1
            self._problem(c, "markers", f"stamp_past: marker {marker.name} at {marker.t:.3f} s "
                          "is older than the data already processed: dropped")  # fmt: skip
            return False
        return self._push(c, "markers", self.nav.push_marker, (marker,))

    def _release_markers(self) -> None:
        """Push the held markers the data's clock has reached, in stamp order."""
        c = self.counters["markers"]
        while self._held_markers and self._held_markers[0].t <= self.clock_s:
            m = self._held_markers.pop(0)
            if m.t <= self._horizon():
                c.faults["stamp_past"] += 1
                self._problem(c, "markers", f"stamp_past: marker {m.name}: data already "
                              "processed: dropped")  # fmt: skip
            else:
                self._push(c, "markers", self.nav.push_marker, (m,))

    def _horizon(self) -> float:
        """The engine's release horizon: a sample stamped at or before it would be late."""
        return self.nav.reorder_horizon

    def _check_burst(self, role: str, c: TopicCounters, now: float) -> None:
        """Token bucket on the sent times (s): BURST_FACTOR x the input's highest rate, with
        BURST_ALLOWANCE_S of those messages as slack; a message beyond it is a burst."""
        rate = BURST_FACTOR * MAX_RATE_HZ[role]
        capacity = rate * BURST_ALLOWANCE_S
        tokens, last = self._bucket.get(role, (capacity, now))
        tokens = min(capacity, tokens + max(now - last, 0.0) * rate)
        if tokens >= 1.0:
            tokens -= 1.0
        else:
            c.faults["burst"] += 1
            self._problem(c, role, f"burst: over {rate:.0f} messages/s: counted, used")
        self._bucket[role] = (tokens, now)

    def _push(self, c: TopicCounters, role: str, push: Callable, args: tuple) -> bool:
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
            if not finite_estimate(est):  # never a NaN on the wire: withheld and counted
                self.estimates_nonfinite += 1
                self._problem(self.counters["imu"], "imu", f"non-finite estimate at {est.t:.3f} s")
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
            twist_covariance(est, self.angular_variance()),
        )
        msg.header.frame_id = self.map_frame
        msg.child_frame_id = self.base_frame
        return msg

    def angular_variance(self) -> float:
        """(rad/s)^2 of the mean rate over one filter epoch: the white noise plus the bias
        instability of the engine's IMU model (chosen at the alignment with imu_grade auto)."""
        spec = self.nav.imu_spec
        return spec.gyro_arw**2 * self.config.filter_rate_hz + spec.gyro_bias_instability**2

    def _latest_stamp(self) -> float:
        if self.last_estimate is not None:
            return self.last_estimate.t
        return 0.0

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self, stamp: float, now: float) -> Any:
        """diagnostic_msgs/DiagnosticArray of the node's health.

        stamp: header stamp, s (ROS clock); now: a monotonic time, s, for the input rates
        (computed between successive calls). Level: ERROR when the engine failed since the last
        call; WARN when messages were malformed, refused or faulty (``<input>.fault.<kind>``,
        named in the message) since the last call, an input that
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
            for kind, n in c.faults.items():
                values[f"{role}.fault.{kind}"] = n
        values.update(self.latency.report())
        values["estimates_published"] = self.estimates_published
        values["estimates_without_datum"] = self.estimates_without_datum
        values["estimates_nonfinite"] = self.estimates_nonfinite
        values["datum_known"] = "yes" if self.nav.datum is not None else "no"
        values["resets"] = self.resets
        values["engine_errors"] = self.poll_errors
        for key, value in self.nav.diagnostics().items():
            values[f"engine.{key}"] = value

        problems = sum(c.malformed + c.refused for c in self.counters.values())
        new_problems = problems - self._problem_mark
        self._problem_mark = problems
        faults = {
            f"{r}.fault.{k}": n for r, c in self.counters.items() for k, n in c.faults.items()
        }
        new_faults = {k: n - self._fault_mark.get(k, 0) for k, n in faults.items()}
        new_faults = {k: n for k, n in new_faults.items() if n > 0}
        self._fault_mark = faults
        state = str(values.get("engine.state", "?"))
        summary = ", ".join(f"{r} {rates[r]:.1f} Hz" for r in ("imu", "odometer", "mag"))
        new_errors = self.poll_errors - self._error_mark
        self._error_mark = self.poll_errors
        new_nonfinite = self.estimates_nonfinite - self._nonfinite_mark
        self._nonfinite_mark = self.estimates_nonfinite
        lost = getattr(self.nav, "lost_since", None)
        if lost is not None:
            level, message = ERROR, f"position lost since t = {lost:.3f} s: {self.nav.lost_reason}"
        elif new_errors:
            level, message = ERROR, f"engine failed {new_errors} time(s) since the last report"
        elif new_nonfinite:
            level = ERROR
            message = f"{new_nonfinite} non-finite estimate(s) withheld since the last report"
        elif new_problems or new_faults:
            named = ", ".join(f"{k} {n}" for k, n in new_faults.items())
            if new_problems:
                named = f"{new_problems} malformed or refused" + (f", {named}" if named else "")
            level, message = WARN, f"since the last report: {named}; {summary}"
        elif stopped:
            level, message = WARN, f"no {' and no '.join(stopped)} data since the last report"
        elif clock := str(values.get("engine.imu_clock", "")):
            level, message = WARN, clock  # re-timed (live_guard): said for as long as it holds
        elif misfit := self.nav.model_warnings():
            level, message = WARN, misfit[0]
        elif sum(received.values()) == 0:
            level, message = OK, "waiting for data"
        elif self.nav.datum is None:
            level, message = OK, f"{state}, waiting for the first marker (datum); {summary}"
        else:
            level, message = OK, f"{state}; {summary}"
        return level, message, values
