"""Sensor sources of the driver nodes, without rclpy: parsers, calibration, pacing, stamping.

Three kinds of sensor (``imu``, ``odometer``, ``mag``) and three sources:

``serial``: a simple ASCII line protocol, one sample per line (NMEA-like)::

    $PNIMU,<t>,<gx>,<gy>,<gz>,<ax>,<ay>,<az>*<cs>
    $PNODO,<t>,<ticks>*<cs>
    $PNMAG,<t>,<mx>,<my>,<mz>*<cs>

  ``t``: device clock, seconds (any origin; increasing). ``gx..gz``: angular rate in ``imu_link``,
  rad/s (times ``gyro_scale``), ``ax..az``: specific force in ``imu_link``, m/s^2 (times
  ``accel_scale``), both the MEAN over the interval since the previous sample. ``ticks``: the
  cumulative signed encoder count (integer). ``mx..mz``: magnetic field in ``imu_link``,
  microtesla (times ``field_scale`` gives tesla; default 1e-6). ``*<cs>`` is optional: two hex
  digits, XOR of all characters between ``$`` and ``*``; when present it must match. Lines end
  with ``\\n`` or ``\\r\\n``; empty lines and lines starting with ``#`` are ignored; lines of
  another sentence type are ignored (so one device may multiplex several sensors).

``log``: the pig recorder's raw CSV logs, one file per sensor, the same fields without the
  sentence tag: ``t_s,gx,gy,gz,ax,ay,az`` (IMU), ``t_s,ticks`` (odometer), ``t_s,mx,my,mz``
  (magnetometer), same units as above. An optional first header row naming exactly those columns;
  ``#`` comment lines and blank lines are skipped. Rows that do not parse, or whose time does not
  increase, are counted and skipped.

``sim``: :func:`pipe_nav_core.sim.simulate` (scenario, seed): samples already in SI units,
  odometer as distance and speed (no ticks), marker passages included.

Everything here is plain Python so the decoding is unit-tested without ROS.
"""

from __future__ import annotations

import heapq
import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from pipe_nav_core import ConfigError, Marker

KINDS = ("imu", "odometer", "mag")
SENTENCES = {"imu": "PNIMU", "odometer": "PNODO", "mag": "PNMAG"}
CSV_COLUMNS = {
    "imu": ("t_s", "gx", "gy", "gz", "ax", "ay", "az"),
    "odometer": ("t_s", "ticks"),
    "mag": ("t_s", "mx", "my", "mz"),
}


class ProtocolError(ValueError):
    """A line or CSV row that cannot be decoded; the message says why."""


# --------------------------------------------------------------------------------------------
# Samples (SI units, frames of INTERFACES.md)


@dataclass(frozen=True)
class ImuSample:
    """t: s (source clock); gyro: rad/s, accel: m/s^2, both imu_link, mean over the interval."""

    t: float
    gyro: tuple[float, float, float]
    accel: tuple[float, float, float]


@dataclass(frozen=True)
class TickSample:
    """t: s (source clock); ticks: cumulative raw encoder count (before unwrapping)."""

    t: float
    ticks: int


@dataclass(frozen=True)
class OdoSample:
    """t: s; distance: m cumulative along the pipe since the start; speed: m/s forward."""

    t: float
    distance: float
    speed: float


@dataclass(frozen=True)
class MagSample:
    """t: s; field: tesla in imu_link (before hard/soft-iron calibration)."""

    t: float
    field: tuple[float, float, float]


Sample = ImuSample | TickSample | OdoSample | MagSample | Marker


# --------------------------------------------------------------------------------------------
# Decoding


@dataclass(frozen=True)
class Scales:
    """Raw-unit to SI factors: gyro -> rad/s, accel -> m/s^2, field -> tesla."""

    gyro: float = 1.0
    accel: float = 1.0
    field: float = 1e-6


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ProtocolError(f"{what} is not a number: {text.strip()!r}") from None
    if not math.isfinite(value):
        raise ProtocolError(f"{what} is not finite: {text.strip()!r}")
    return value


def decode_fields(kind: str, fields: Sequence[str], scales: Scales = Scales()) -> Sample:
    """Decode the comma-separated fields of one sample (time first) into an SI sample."""
    names = CSV_COLUMNS[kind]
    if len(fields) != len(names):
        raise ProtocolError(
            f"{kind} sample needs {len(names)} fields ({','.join(names)}), got {len(fields)}"
        )
    t = _number(fields[0], "time")
    if kind == "odometer":
        text = fields[1].strip()
        try:
            ticks = int(text)
        except ValueError:
            raise ProtocolError(f"ticks is not an integer: {text!r}") from None
        return TickSample(t, ticks)
    v = [_number(f, n) for f, n in zip(fields[1:], names[1:], strict=True)]
    if kind == "imu":
        g, a = scales.gyro, scales.accel
        return ImuSample(t, (v[0] * g, v[1] * g, v[2] * g), (v[3] * a, v[4] * a, v[5] * a))
    s = scales.field
    return MagSample(t, (v[0] * s, v[1] * s, v[2] * s))


def nmea_checksum(body: str) -> str:
    """Two upper-case hex digits: XOR of the characters of ``body`` (between ``$`` and ``*``)."""
    cs = 0
    for ch in body.encode("ascii", errors="replace"):
        cs ^= ch
    return f"{cs:02X}"


def format_line(sample: ImuSample | TickSample | MagSample, scales: Scales = Scales()) -> str:
    """The line-protocol sentence of a sample (with checksum): the inverse of parse_line."""
    if isinstance(sample, ImuSample):
        vals = [x / scales.gyro for x in sample.gyro] + [x / scales.accel for x in sample.accel]
        body = "PNIMU," + ",".join([repr(float(sample.t))] + [repr(float(x)) for x in vals])
    elif isinstance(sample, TickSample):
        body = f"PNODO,{float(sample.t)!r},{int(sample.ticks)}"
    else:
        vals = [x / scales.field for x in sample.field]
        body = "PNMAG," + ",".join([repr(float(sample.t))] + [repr(float(x)) for x in vals])
    return f"${body}*{nmea_checksum(body)}\r\n"


def parse_line(
    line: str | bytes, kind: str, scales: Scales = Scales()
) -> ImuSample | TickSample | MagSample | None:
    """Decode one line of the serial protocol for sensor ``kind``.

    Returns None for lines to skip silently (blank, ``#`` comment, another sentence type);
    raises ProtocolError for a line of this kind that is damaged (bad checksum, fields).
    """
    if isinstance(line, bytes):
        line = line.decode("ascii", errors="replace")
    text = line.strip()
    if not text or text.startswith("#"):
        return None
    if not text.startswith("$"):
        raise ProtocolError(f"line does not start with '$': {text[:40]!r}")
    body, star, cs = text[1:].partition("*")
    if star and (len(cs) != 2 or cs.upper() != nmea_checksum(body)):
        raise ProtocolError(f"checksum mismatch ({cs!r} != {nmea_checksum(body)}): {text[:60]!r}")
    fields = body.split(",")
    if fields[0] != SENTENCES[kind]:
        if fields[0] in SENTENCES.values():
            return None
        raise ProtocolError(f"unknown sentence {fields[0]!r}")
    sample = decode_fields(kind, fields[1:], scales)
    assert not isinstance(sample, (OdoSample, Marker))
    return sample


class LineAssembler:
    """Cuts a byte stream (serial reads of any size) into complete lines.

    Lines longer than ``max_length`` bytes (garbage, wrong baud rate) are discarded and counted,
    each once: the rest of a line dropped before its end arrived is dropped too, up to its end.
    """

    def __init__(self, max_length: int = 512) -> None:
        self.max_length = max_length
        self._buf = b""
        self._skipping = False
        self.overlong = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Complete lines (without the end of line) found after adding ``data``."""
        self._buf += data
        *lines, self._buf = self._buf.split(b"\n")
        if self._skipping:
            if lines:
                lines.pop(0)  # the end of the overlong line dropped before
                self._skipping = False
            else:
                self._buf = b""
        if len(self._buf) > self.max_length:
            self._buf = b""
            self.overlong += 1
            self._skipping = True
        out = []
        for line in lines:
            if len(line) > self.max_length:
                self.overlong += 1
            else:
                out.append(line.rstrip(b"\r"))
        return out


@dataclass
class ReadStats:
    """Counters of a source: lines or rows read, samples accepted, rows skipped and why."""

    lines: int = 0
    samples: int = 0
    malformed: int = 0
    non_increasing: int = 0
    last_error: str = ""

    def as_dict(self) -> dict[str, int | str]:
        return {
            "lines": self.lines,
            "samples": self.samples,
            "malformed": self.malformed,
            "non_increasing": self.non_increasing,
            "last_error": self.last_error,
        }


def read_csv_log(
    stream: TextIO | Iterable[str],
    kind: str,
    scales: Scales = Scales(),
    stats: ReadStats | None = None,
    on_error: Callable[[int, str], None] | None = None,
) -> Iterator[ImuSample | TickSample | MagSample]:
    """Iterate the samples of a recorder CSV log (lazily: logs may be days long).

    A first non-comment row that is not numeric must be the header ``CSV_COLUMNS[kind]``
    (else ConfigError: wrong file for this sensor). Damaged rows and rows whose time does not
    increase are counted in ``stats`` and reported to ``on_error(line_number, reason)``.
    """
    stats = stats if stats is not None else ReadStats()
    expected = CSV_COLUMNS[kind]
    last_t = -math.inf
    first = True
    for number, raw in enumerate(stream, start=1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        stats.lines += 1
        fields = [f.strip() for f in text.split(",")]
        if first:
            first = False
            try:
                float(fields[0])
            except ValueError:
                header = tuple(f.lower() for f in fields)
                if header != expected:
                    raise ConfigError(
                        f"{kind} log header must be {','.join(expected)}, not {text[:80]!r}"
                    ) from None
                continue
        try:
            sample = decode_fields(kind, fields, scales)
        except ProtocolError as exc:
            stats.malformed += 1
            stats.last_error = f"line {number}: {exc}"
            if on_error is not None:
                on_error(number, str(exc))
            continue
        if sample.t <= last_t:
            stats.non_increasing += 1
            stats.last_error = f"line {number}: time {sample.t} does not increase"
            if on_error is not None:
                on_error(number, f"time {sample.t} does not increase (previous {last_t})")
            continue
        last_t = sample.t
        stats.samples += 1
        assert not isinstance(sample, (OdoSample, Marker))
        yield sample


# --------------------------------------------------------------------------------------------
# Calibration


class TickOdometer:
    """Encoder counts -> distance and speed.

    distance = (ticks - first ticks) * circumference / ticks_per_turn (m, since the first
    sample); speed = distance change over the last ``speed_window_s`` seconds (m/s; 0 for the
    first sample). ``counter_bits`` > 0 unwraps a counter that wraps modulo 2**bits (signed or
    unsigned alike); 0 means the counter never wraps.
    """

    def __init__(
        self,
        circumference_m: float,
        ticks_per_turn: int,
        speed_window_s: float = 0.2,
        counter_bits: int = 0,
    ) -> None:
        if not (math.isfinite(circumference_m) and circumference_m > 0):
            raise ConfigError(f"wheel_circumference_m must be > 0, not {circumference_m!r}")
        if ticks_per_turn <= 0:
            raise ConfigError(f"ticks_per_turn must be a positive integer, not {ticks_per_turn!r}")
        if not (math.isfinite(speed_window_s) and speed_window_s > 0):
            raise ConfigError(f"speed_window_s must be > 0, not {speed_window_s!r}")
        if not 0 <= counter_bits <= 64:
            raise ConfigError(f"counter_bits must be 0 (no wrap) to 64, not {counter_bits!r}")
        self.metres_per_tick = circumference_m / ticks_per_turn
        self.speed_window_s = speed_window_s
        self.modulus = 1 << counter_bits if counter_bits else 0
        self.reset()

    def reset(self) -> None:
        self._first: int | None = None
        self._last_raw = 0
        self._unwrapped = 0
        self._history: deque[tuple[float, float]] = deque()

    def update(self, t: float, ticks: int) -> tuple[float, float]:
        """Feed one count at time t (s); returns (distance m, speed m/s)."""
        if self._first is None:
            self._first = ticks
            self._unwrapped = ticks
        else:
            step = ticks - self._last_raw
            if self.modulus:
                half = self.modulus // 2
                step = (step + half) % self.modulus - half
            self._unwrapped += step
        self._last_raw = ticks
        distance = (self._unwrapped - self._first) * self.metres_per_tick
        hist = self._history
        hist.append((t, distance))
        # keep one entry at or before the window start so the window is fully spanned
        while len(hist) > 2 and hist[1][0] <= t - self.speed_window_s:
            hist.popleft()
        t0, d0 = hist[0]
        speed = (distance - d0) / (t - t0) if t > t0 else 0.0
        return distance, speed


@dataclass(frozen=True)
class MagCalibration:
    """field = soft_iron @ (raw - hard_iron); hard_iron tesla in imu_link, soft_iron 3x3."""

    hard_iron: tuple[float, float, float] = (0.0, 0.0, 0.0)
    soft_iron: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        if len(self.hard_iron) != 3 or not all(math.isfinite(x) for x in self.hard_iron):
            raise ConfigError(f"hard_iron must be 3 finite numbers (T), not {self.hard_iron!r}")
        if len(self.soft_iron) != 9 or not all(math.isfinite(x) for x in self.soft_iron):
            raise ConfigError(
                f"soft_iron must be 9 finite numbers (3x3 row-major), not {self.soft_iron!r}"
            )

    def apply(self, field: Sequence[float]) -> tuple[float, float, float]:
        d = [field[i] - self.hard_iron[i] for i in range(3)]
        s = self.soft_iron
        return (
            s[0] * d[0] + s[1] * d[1] + s[2] * d[2],
            s[3] * d[0] + s[4] * d[1] + s[5] * d[2],
            s[6] * d[0] + s[7] * d[1] + s[8] * d[2],
        )


# --------------------------------------------------------------------------------------------
# Time: stamps and pacing


class DeviceClockSync:
    """Maps a device clock onto the host (ROS) clock for serial sensors.

    The offset host - device is the smallest (least delayed) one seen, allowed to grow by at most
    ``max_drift`` s per s of device time so it follows clock drift; a device time that goes
    backwards (device reset) restarts the estimate.
    """

    def __init__(self, max_drift: float = 1e-4) -> None:
        self.max_drift = max_drift
        self.offset: float | None = None
        self._last_t: float | None = None

    def stamp(self, t_device: float, arrival: float) -> float:
        """Host-clock stamp (s) of a sample taken at device time t_device, received at arrival."""
        observed = arrival - t_device
        if self.offset is None or self._last_t is None or t_device < self._last_t:
            self.offset = observed
        else:
            grown = self.offset + self.max_drift * (t_device - self._last_t)
            self.offset = min(grown, observed)
        self._last_t = t_device
        return t_device + self.offset


@dataclass(frozen=True)
class Timeline:
    """Pacing and stamping of a replayed source (log or sim).

    The sample with source time ``t`` is due at wall time ``start + (t - t_ref) / rate``
    (``time.time()`` seconds) and is stamped ``t`` (``restamp`` False: the source's own clock) or
    ``start + (t - t_ref)`` (``restamp`` True: the run moved onto the ROS clock, sensor time
    intervals kept).
    """

    t_ref: float
    start: float
    rate: float = 1.0
    restamp: bool = False

    def due(self, t: float) -> float:
        return self.start + (t - self.t_ref) / self.rate

    def stamp(self, t: float) -> float:
        return self.start + (t - self.t_ref) if self.restamp else t


def merge_by_time(*streams: Iterable[Sample]) -> Iterator[Sample]:
    """Merge time-ordered sample streams into one time-ordered stream."""
    return heapq.merge(*streams, key=lambda s: s.t)


def play(
    samples: Iterable[Sample],
    timeline: Timeline,
    emit: Callable[[Sample, float], None],
    stop: Callable[[float], bool],
    now: Callable[[], float] = time.time,
) -> int:
    """Emit each sample at its due time with its stamp; returns how many were emitted.

    ``stop(timeout)`` waits up to ``timeout`` seconds and returns True to abort (for example a
    ``threading.Event.wait``); samples already due are emitted without waiting.
    """
    count = 0
    for sample in samples:
        due = timeline.due(sample.t)
        while True:
            wait = due - now()
            if wait <= 0:
                break
            if stop(min(wait, 0.5)):
                return count
        emit(sample, timeline.stamp(sample.t))
        count += 1
    return count


# --------------------------------------------------------------------------------------------
# Sources


def log_samples(
    path: str | Path,
    kind: str,
    scales: Scales = Scales(),
    stats: ReadStats | None = None,
    on_error: Callable[[int, str], None] | None = None,
) -> Iterator[ImuSample | TickSample | MagSample]:
    """Samples of a recorder CSV log file (see the module docstring); the file stays open while
    iterating and is closed at the end."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"log_file {str(p)!r} does not exist")
    with p.open("r", encoding="utf-8", errors="replace", newline="") as f:
        yield from read_csv_log(f, kind, scales, stats, on_error)


def sim_samples(kind: str, scenario: str, seed: int) -> tuple[list[Sample], float]:
    """The samples of one sensor of a simulated run, and the run's time origin (s).

    The time origin is the earliest sample of any sensor of the run, so the three driver nodes
    running the same scenario and seed share it. The odometer stream includes the marker passages.
    """
    from pipe_nav_core import simulate  # only this source needs the simulator

    try:
        run = simulate(scenario, seed)
    except (KeyError, ValueError) as exc:
        raise ConfigError(f"scenario {scenario!r}: {exc}") from None
    log = run.log
    firsts = [float(a.t[0]) for a in (log.imu, log.odometer, log.mag) if len(a.t)]
    firsts += [float(m.t) for m in log.markers]
    t_ref = min(firsts) if firsts else 0.0
    out: list[Sample]
    if kind == "imu":
        out = [
            ImuSample(float(t), _vec(g), _vec(a))
            for t, g, a in zip(log.imu.t, log.imu.gyro, log.imu.accel, strict=True)
        ]
    elif kind == "mag":
        out = [MagSample(float(t), _vec(f)) for t, f in zip(log.mag.t, log.mag.field, strict=True)]
    else:
        odo = log.odometer
        odo_samples = [
            OdoSample(float(t), float(d), float(s))
            for t, d, s in zip(odo.t, odo.distance, odo.speed, strict=True)
        ]
        markers = sorted(log.markers, key=lambda m: m.t)
        out = list(merge_by_time(odo_samples, markers))
    return out, t_ref


def _vec(v: Any) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))
