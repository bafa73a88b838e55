"""Reading ROS 2 bags (MCAP) into SensorLogs: whole (:func:`read_bag`) or streamed in time chunks
(:func:`iter_bag`), plus cheap metadata (:func:`bag_info`, :func:`bag_time_range`).

A bag is a single ``.mcap`` file or a rosbag2 directory (``metadata.yaml`` listing its ``.mcap``
files, read in that order; without metadata.yaml its ``*.mcap`` files in name order). Sample
times are the header stamps, never the log times.

Checks, in this order, per topic, in recording (file) order (the skip reasons are the
``SKIP_*`` constants of :mod:`.topics`, counted in the :class:`BagReport`):

1. the channel must carry the expected type (``unknown_type`` otherwise, with a warning);
2. the payload must deserialize (``bad_cdr``); NaN/inf values are dropped (``nan``);
3. an isolated stamp more than ``TIME_JUMP_S`` ahead of both its neighbours is a clock glitch
   (``time_jump``);
4. a stamp more than ``REORDER_WINDOW_S`` behind the newest accepted stamp of its topic is
   dropped (``non_monotonic``); smaller disorder is repaired by sorting;
5. after sorting, repeated stamps keep the first message (``duplicate``).

Markers only go through 1, 2 and duplicate removal (same name and stamp), then are sorted.
Streaming (:func:`iter_bag`) holds back ``lag_seconds`` of data behind the newest stamp before it
hands out a time chunk; a message that arrives after its chunk went out is dropped (``late``,
with a warning), so in the normal case the chunks concatenate exactly to :func:`read_bag`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError, McapFormatError
from ..types import (
    ImuSamples,
    MagSamples,
    Marker,
    OdometerSamples,
    SensorLog,
    empty_imu,
    empty_mag,
    empty_odometer,
)
from . import cdr
from .mcapread import (
    McapScanner,
    MessageBatch,
    chunk_messages,
    read_summary,
)
from .rosmsg import (
    imu_from_msg,
    jazzy_typestore,
    mag_from_msg,
    marker_from_msg,
    wheel_from_msg,
)
from .stamps import NS_PER_S, ns_to_sec, sec_to_ns_scalar
from .topics import (
    DEFAULT_TOPICS,
    ROLE_TYPES,
    SKIP_BAD_CDR,
    SKIP_CORRUPT_CHUNK,
    SKIP_DUPLICATE,
    SKIP_LATE,
    SKIP_NAN,
    SKIP_NON_MONOTONIC,
    SKIP_TIME_JUMP,
    SKIP_UNKNOWN_TYPE,
    BagError,
    BagReport,
    TopicNames,
    normalize_type,
)

REORDER_WINDOW_S = 0.5  # s: stamps this much out of order are re-sorted, older ones dropped
TIME_JUMP_S = 1.0  # s: an isolated stamp this far ahead of both neighbours is a glitch
EMIT_LAG_S = 5.0  # s: streaming holds back this much data behind the newest stamp
READ_WORKERS_ENV = "PIPE_NAV_READ_WORKERS"  # threads that unpack the chunks (0: none)

_ROLES = ("imu", "odometer", "mag", "markers")
_LAYOUT = {
    "imu": cdr.IMU,
    "odometer": cdr.ODOMETRY,
    "mag": cdr.MAGNETIC_FIELD,
    "markers": cdr.NAVSATFIX,
}
_FIELDS = {
    "imu": ("sec", "nanosec", "angular_velocity", "linear_acceleration"),
    "odometer": ("sec", "nanosec", "position", "linear"),
    "mag": ("sec", "nanosec", "magnetic_field"),
    "markers": (
        "sec",
        "nanosec",
        "frame_id",
        "latitude",
        "longitude",
        "altitude",
        "position_covariance",
        "position_covariance_type",
    ),
}
_MISSING_HINT = {
    "imu": "",
    "odometer": "",
    "mag": " (optional magnetometer)",
    "markers": " (give the markers with a CSV file)",
}


# ----------------------------------------------------------------------------- files


def bag_files(path: str | os.PathLike[str]) -> list[Path]:
    """The MCAP files of a bag, in reading order (raises BagError with a one-line reason)."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such file or directory")
    if p.is_file() and p.name == "metadata.yaml":
        p = p.parent
    if p.is_file():
        return [p]
    meta = p / "metadata.yaml"
    if meta.is_file():
        try:
            from ruamel.yaml import YAML

            doc = YAML(typ="safe").load(meta.read_text())
            info = doc["rosbag2_bagfile_information"]
            storage = str(info.get("storage_identifier", "mcap"))
            names = [PurePath(str(x)).name for x in info.get("relative_file_paths", [])]
            compression = str(info.get("compression_mode", "") or "").lower()
        except Exception as exc:
            raise BagError(
                f"{meta}: unreadable rosbag2 metadata ({exc.__class__.__name__})"
            ) from None
        if storage != "mcap":
            raise BagError(
                f"{p}: storage '{storage}' is not supported, only mcap "
                "(convert with: ros2 bag convert)"
            )
        if compression == "file":
            raise BagError(
                f"{p}: file-compressed rosbag2 bags are not supported (decompress first)"
            )
        files = [p / n for n in names]
        present = [f for f in files if f.is_file()]
        if not present:
            raise BagError(f"{p}: none of the files listed in metadata.yaml exist")
        return files
    files = sorted(x for x in p.iterdir() if x.suffix == ".mcap" and x.is_file())
    if not files:
        raise BagError(f"{p}: directory has neither metadata.yaml nor .mcap files")
    return files


# ----------------------------------------------------------------------------- per-topic state


@dataclass
class _Pieces:
    """Decoded samples of one topic in arrival order: stamps (ns) and value arrays."""

    ns: NDArray[np.int64]
    values: dict[str, NDArray]

    def take(self, idx: NDArray) -> _Pieces:
        return _Pieces(self.ns[idx], {k: v[idx] for k, v in self.values.items()})

    def __len__(self) -> int:
        return len(self.ns)

    @staticmethod
    def concat(parts: Sequence[_Pieces], keys: Sequence[str]) -> _Pieces:
        if len(parts) == 1:
            return parts[0]
        return _Pieces(
            np.concatenate([p.ns for p in parts]),
            {k: np.concatenate([p.values[k] for p in parts]) for k in keys},
        )


_VALUE_KEYS = {
    "imu": ("gyro", "accel"),
    "odometer": ("distance", "speed"),
    "mag": ("field",),
    "markers": ("marker",),
}


def _empty_pieces(role: str) -> _Pieces:
    shapes = {"gyro": (0, 3), "accel": (0, 3), "distance": (0,), "speed": (0,), "field": (0, 3)}
    vals: dict[str, NDArray] = {}
    for k in _VALUE_KEYS[role]:
        vals[k] = np.empty(0, dtype=object) if k == "marker" else np.zeros(shapes[k])
    return _Pieces(np.zeros(0, dtype=np.int64), vals)


@dataclass
class _TopicState:
    topic: str
    role: str
    report: BagReport
    run_max: int | None = None  # newest accepted stamp, ns
    prev_ns: int | None = None  # stamp of the previous message in arrival order
    pending: _Pieces | None = None  # last message, held for the time-jump test
    buffer: list[_Pieces] = field(default_factory=list)
    boundary: int | None = None  # stamps below this were handed out already (streaming)
    last_emitted: int | None = None
    emitted_markers: set[tuple[str, int]] = field(default_factory=set)
    seen: int = 0

    @property
    def keys(self) -> tuple[str, ...]:
        return _VALUE_KEYS[self.role]

    def ingest(self, p: _Pieces, final: bool = False) -> None:
        """Add decoded, finite samples (arrival order)."""
        if self.role == "markers":
            self._ingest_markers(p)
            return
        if self.pending is not None:
            p = _Pieces.concat([self.pending, p], self.keys) if len(p) else self.pending
            self.pending = None
        if len(p) == 0:
            return
        ns = p.ns
        m = len(ns)
        jump = np.int64(int(TIME_JUMP_S * NS_PER_S))
        prev = np.empty(m, dtype=np.int64)
        prev[1:] = ns[:-1]
        prev[0] = ns[0] if self.prev_ns is None else self.prev_ns
        hold_last = not final
        nxt = np.empty(m, dtype=np.int64)
        nxt[:-1] = ns[1:]
        nxt[-1] = ns[-1]  # the last one is decided with the next batch (or accepted at the end)
        ahead_of_prev = ns - prev > jump
        if self.prev_ns is None:
            ahead_of_prev[0] = True  # the very first message: judged by its successor only
        spike = ahead_of_prev & (ns - nxt > jump)
        if hold_last:
            self.pending = p.take(np.array([m - 1]))
            keep_n = m - 1
        else:
            keep_n = m
        self.prev_ns = int(ns[keep_n - 1]) if keep_n > 0 else self.prev_ns
        if keep_n == 0:
            return
        spike = spike[:keep_n]
        ns = ns[:keep_n]
        if spike.any():
            self.report.add_skipped(self.topic, SKIP_TIME_JUMP, int(spike.sum()))
        # Running maximum over everything before each sample (spikes excluded).
        ns_f = np.where(spike, np.iinfo(np.int64).min, ns)
        cm = np.maximum.accumulate(ns_f)
        before = np.empty(keep_n, dtype=np.int64)
        before[0] = np.iinfo(np.int64).min
        before[1:] = cm[:-1]
        if self.run_max is not None:
            before = np.maximum(before, self.run_max)
        window = np.int64(int(REORDER_WINDOW_S * NS_PER_S))
        lo = np.where(before == np.iinfo(np.int64).min, before, before - window)
        accept = ~spike & (ns > lo)
        n_back = int((~spike & ~accept).sum())
        if n_back:
            self.report.add_skipped(self.topic, SKIP_NON_MONOTONIC, n_back)
        if self.boundary is not None:
            dup = accept & (ns == self.last_emitted) if self.last_emitted is not None else None
            if dup is not None and dup.any():
                self.report.add_skipped(self.topic, SKIP_DUPLICATE, int(dup.sum()))
                accept &= ~dup
            late = accept & (ns < self.boundary)
            if late.any():
                self.report.add_skipped(self.topic, SKIP_LATE, int(late.sum()))
                accept &= ~late
        if cm.size and cm[-1] != np.iinfo(np.int64).min:
            top = int(cm[-1])
            self.run_max = top if self.run_max is None else max(self.run_max, top)
        idx = np.flatnonzero(accept)
        if len(idx):
            self.buffer.append(p.take(idx))

    def _ingest_markers(self, p: _Pieces) -> None:
        if len(p) == 0:
            return
        if self.boundary is not None:
            late = p.ns < self.boundary
            for i in np.flatnonzero(late):
                mk: Marker = p.values["marker"][i]
                self.report.add_skipped(self.topic, SKIP_LATE)
                self.report.warn(
                    f"{self.topic}: marker {mk.name!r} (t={mk.t:.3f} s) arrived after its time "
                    "chunk was handed out and was dropped; read the whole bag or give the "
                    "markers as a CSV file"
                )
            p = p.take(np.flatnonzero(~late))
        if len(p):
            self.buffer.append(p)

    def flush_pending(self) -> None:
        if self.pending is not None:
            p, self.pending = self.pending, None
            self.ingest(p, final=True)

    def high_water(self) -> int | None:
        return self.run_max

    def emit(self, upto: int | None) -> _Pieces:
        """Sorted, de-duplicated samples with stamp < upto (all when None)."""
        if not self.buffer:
            if upto is not None:
                self.boundary = upto if self.boundary is None else max(self.boundary, upto)
            return _empty_pieces(self.role)
        allp = _Pieces.concat(self.buffer, self.keys)
        order = np.argsort(allp.ns, kind="stable")
        allp = allp.take(order)
        if upto is None:
            out, rest = allp, None
        else:
            cut = int(np.searchsorted(allp.ns, upto, side="left"))
            out = allp.take(np.arange(cut))
            rest = allp.take(np.arange(cut, len(allp))) if cut < len(allp) else None
        self.buffer = [rest] if rest is not None and len(rest) else []
        if self.role == "markers":
            keep = []
            for i, mk in enumerate(out.values["marker"]):
                key = (mk.name, int(out.ns[i]))
                if key in self.emitted_markers:
                    self.report.add_skipped(self.topic, SKIP_DUPLICATE)
                    continue
                self.emitted_markers.add(key)
                keep.append(i)
            out = out.take(np.asarray(keep, dtype=np.int64))
        elif len(out):
            dup = np.zeros(len(out), dtype=bool)
            dup[1:] = out.ns[1:] == out.ns[:-1]
            if self.last_emitted is not None:
                dup[0] = out.ns[0] == self.last_emitted
            if dup.any():
                self.report.add_skipped(self.topic, SKIP_DUPLICATE, int(dup.sum()))
                out = out.take(np.flatnonzero(~dup))
            if len(out):
                self.last_emitted = int(out.ns[-1])
        if upto is not None:
            self.boundary = upto if self.boundary is None else max(self.boundary, upto)
        self.report.counts[self.topic] = self.report.counts.get(self.topic, 0) + len(out)
        return out


# ----------------------------------------------------------------------------- decoding


def _decode_role(
    role: str, batch: MessageBatch, sel: NDArray[np.int64], topic: str, report: BagReport
) -> _Pieces:
    """Decode the messages ``sel`` of a batch for a role; returns finite samples in order."""
    starts = batch.payload_start[sel]
    sizes = batch.size[sel]
    vals, ok = cdr.decode_batch(_LAYOUT[role], batch.buf, starts, sizes, _FIELDS[role])
    good = np.flatnonzero(ok)
    if role == "imu" and len(good) and not report.imu_noise_declared:
        report.imu_noise_declared = _declared_noise(batch.buf, starts[good[:1]], sizes[good[:1]])
    ns_parts: list[NDArray[np.int64]] = []
    pos_parts: list[NDArray[np.int64]] = []
    val_parts: list[dict[str, NDArray]] = []
    if len(good):
        ns = vals["sec"].astype(np.int64) * NS_PER_S + vals["nanosec"].astype(np.int64)
        ns_parts.append(ns)
        pos_parts.append(good)
        val_parts.append(_role_values(role, vals))
    bad = np.flatnonzero(~ok)
    if len(bad):
        fb_ns, fb_pos, fb_vals, n_fail = _fallback(role, batch, starts, sizes, bad)
        if n_fail:
            report.add_skipped(topic, SKIP_BAD_CDR, n_fail)
        if len(fb_ns):
            ns_parts.append(fb_ns)
            pos_parts.append(fb_pos)
            val_parts.append(fb_vals)
    if not ns_parts:
        return _empty_pieces(role)
    keys = _VALUE_KEYS[role]
    p = _Pieces(
        np.concatenate(ns_parts),
        {k: np.concatenate([v[k] for v in val_parts]) for k in keys},
    )
    if len(ns_parts) > 1:
        p = p.take(np.argsort(np.concatenate(pos_parts), kind="stable"))
    finite = _finite(role, p)
    if not finite.all():
        report.add_skipped(topic, SKIP_NAN, int((~finite).sum()))
        p = p.take(np.flatnonzero(finite))
    return p


def _role_values(role: str, vals: dict[str, object]) -> dict[str, NDArray]:
    if role == "imu":
        return {"gyro": vals["angular_velocity"], "accel": vals["linear_acceleration"]}
    if role == "odometer":
        return {"distance": vals["position"][:, 0], "speed": vals["linear"][:, 0]}
    if role == "mag":
        return {"field": vals["magnetic_field"]}
    markers = np.empty(len(vals["frame_id"]), dtype=object)
    for i in range(len(markers)):
        markers[i] = _marker_from_values(vals, i)
    return {"marker": markers}


class _NavSatView:
    """Attribute view over decoded NavSatFix columns (for marker_from_msg)."""

    class _Stamp:
        def __init__(self, sec: int, nanosec: int) -> None:
            self.sec = sec
            self.nanosec = nanosec

    class _Header:
        def __init__(self, stamp: object, frame_id: str) -> None:
            self.stamp = stamp
            self.frame_id = frame_id

    def __init__(self, vals: dict[str, object], i: int) -> None:
        self.header = self._Header(
            self._Stamp(int(vals["sec"][i]), int(vals["nanosec"][i])), vals["frame_id"][i]
        )
        self.latitude = float(vals["latitude"][i])
        self.longitude = float(vals["longitude"][i])
        self.altitude = float(vals["altitude"][i])
        self.position_covariance = vals["position_covariance"][i]
        self.position_covariance_type = int(vals["position_covariance_type"][i])


def _marker_from_values(vals: dict[str, object], i: int) -> Marker:
    return marker_from_msg(_NavSatView(vals, i))


def _fallback(
    role: str, batch: MessageBatch, starts: NDArray, sizes: NDArray, bad: NDArray
) -> tuple[NDArray[np.int64], NDArray[np.int64], dict[str, NDArray], int]:
    """Generic (rosbags) deserialization of the messages the vectorized decoder refused."""
    ts = jazzy_typestore()
    typename = ROLE_TYPES[role]
    raw = batch.buf
    ns_l: list[int] = []
    pos_l: list[int] = []
    cols: dict[str, list] = {k: [] for k in _VALUE_KEYS[role]}
    fails = 0
    for j in bad.tolist():
        a = int(starts[j])
        b = a + int(sizes[j])
        try:
            msg = ts.deserialize_cdr(raw[a:b].tobytes(), typename)
            stamp = msg.header.stamp
            ns = int(stamp.sec) * NS_PER_S + int(stamp.nanosec)
            if role == "imu":
                _, g, acc = imu_from_msg(msg)
                cols["gyro"].append(g)
                cols["accel"].append(acc)
            elif role == "odometer":
                _, d, v = wheel_from_msg(msg)
                cols["distance"].append(d)
                cols["speed"].append(v)
            elif role == "mag":
                _, fld = mag_from_msg(msg)
                cols["field"].append(fld)
            else:
                cols["marker"].append(marker_from_msg(msg))
        except Exception:
            fails += 1
            continue
        ns_l.append(ns)
        pos_l.append(j)
    out: dict[str, NDArray] = {}
    for k, v in cols.items():
        if k == "marker":
            arr = np.empty(len(v), dtype=object)
            for i, x in enumerate(v):
                arr[i] = x
            out[k] = arr
        elif k in ("gyro", "accel", "field"):
            out[k] = np.asarray(v, dtype=np.float64).reshape(-1, 3)
        else:
            out[k] = np.asarray(v, dtype=np.float64).reshape(-1)
    return np.asarray(ns_l, dtype=np.int64), np.asarray(pos_l, dtype=np.int64), out, fails


def _finite(role: str, p: _Pieces) -> NDArray[np.bool_]:
    if role == "markers":
        return np.array(
            [
                all(math.isfinite(x) for x in (m.t, m.lat, m.lon, m.alt, *m.sigma_enu))
                for m in p.values["marker"]
            ],
            dtype=bool,
        )
    ok = np.ones(len(p), dtype=bool)
    for v in p.values.values():
        f = np.isfinite(v)
        ok &= f.all(axis=1) if f.ndim == 2 else f
    return ok


# ----------------------------------------------------------------------------- the reader


def read_workers(workers: int | None = None) -> int:
    """Threads that unpack the zstd chunks (decompress, CRC check, locate the messages) ahead
    of the decoding and the checks: ``workers`` when given (0: none, all in the calling
    thread), else the environment variable ``PIPE_NAV_READ_WORKERS``, else one when there are
    two cores or more (more do not pay: the decoding and the checks hold the GIL, and they are
    what is left to the calling thread). InputError (a ValueError) for a negative or
    non-integer count."""
    if workers is None:
        env = os.environ.get(READ_WORKERS_ENV, "").strip()
        if not env:
            return 1 if (os.cpu_count() or 1) >= 2 else 0
        try:
            workers = int(env)
        except ValueError:
            raise InputError(f"{READ_WORKERS_ENV}={env!r}: not a whole number of threads") from None
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise InputError(f"read workers must be a whole number >= 0, got {workers!r}")
    return workers


class _BagReader:
    def __init__(
        self,
        path: str | os.PathLike[str],
        topics: TopicNames,
        report: BagReport | None,
        workers: int | None = None,
    ):
        self.path = Path(path)
        self.workers = read_workers(workers)
        self.files = bag_files(path)
        self.topics = topics
        self.report = report if report is not None else BagReport()
        self.report.path = str(self.path)
        self.report.files = [str(f) for f in self.files]
        by_topic = topics.roles()
        self.states = {role: _TopicState(t, role, self.report) for t, role in by_topic.items()}
        self.role_of = by_topic
        for t in by_topic:
            self.report.counts.setdefault(t, 0)
        self.messages_read = 0
        # Fail early on a single file that is not MCAP at all.
        if len(self.files) == 1:
            self._check_magic(self.files[0])

    def _check_magic(self, f: Path) -> None:
        try:
            McapScanner(f, self.report.warn)
        except McapFormatError as exc:
            raise BagError(f"{f}: {exc}") from None
        except OSError as exc:
            raise BagError(f"{f}: cannot read ({exc.strerror or exc})") from None

    def _batches(self) -> Iterator[tuple[MessageBatch, dict[int, str]]]:
        """(batch, channel id -> role) over every file, with type checks."""
        usable = 0
        for f in self.files:
            if not f.is_file():
                self.report.truncated = True
                self.report.warn(f"{f}: listed in metadata.yaml but missing; skipped")
                continue
            try:
                sc = McapScanner(f, self.report.warn)
            except (McapFormatError, OSError) as exc:
                if len(self.files) == 1:
                    raise BagError(f"{f}: {exc}") from None
                self.report.truncated = True
                self.report.warn(f"{f}: unreadable ({exc}); skipped")
                continue
            usable += 1
            warned: set[int] = set()
            for batch in sc.batches(self.workers):
                roles = self._channel_roles(sc, warned)
                yield batch, roles
            if sc.truncated:
                self.report.truncated = True
            for cid, n in sc.corrupt_messages.items():
                ch = sc.channels.get(cid)
                if ch is not None and ch.topic in self.role_of:
                    self.report.add_skipped(ch.topic, SKIP_CORRUPT_CHUNK, n)
        if usable == 0:
            raise BagError(f"{self.path}: no readable MCAP file")

    def _channel_roles(self, sc: McapScanner, warned: set[int]) -> dict[int, str]:
        roles: dict[int, str] = {}
        for cid, ch in sc.channels.items():
            schema = sc.schemas.get(ch.schema_id)
            typename = normalize_type(schema.name) if schema is not None else ""
            if ch.topic not in self.report.types:
                self.report.types[ch.topic] = typename
            role = self.role_of.get(ch.topic)
            if role is None:
                continue
            expected = ROLE_TYPES[role]
            if typename != expected or ch.message_encoding != "cdr":
                roles[cid] = "!" + role
                if cid not in warned:
                    warned.add(cid)
                    got = typename or "no schema"
                    if ch.message_encoding != "cdr":
                        got += f", encoding {ch.message_encoding}"
                    self.report.warn(
                        f"{ch.topic}: carries {got}, expected {expected} (cdr); "
                        "its messages were skipped"
                    )
                continue
            roles[cid] = role
        return roles

    def _ingest_batch(self, batch: MessageBatch, roles: dict[int, str]) -> None:
        if len(batch) == 0:
            return
        chans = np.unique(batch.channel)
        for cid in chans.tolist():
            role = roles.get(cid)
            if role is None:
                continue
            sel = np.flatnonzero(batch.channel == cid)
            if role.startswith("!"):
                self.report.add_skipped(self.topics_of(role[1:]), SKIP_UNKNOWN_TYPE, len(sel))
                continue
            st = self.states[role]
            st.seen += len(sel)
            self.messages_read += len(sel)
            st.ingest(_decode_role(role, batch, sel, st.topic, self.report))

    def topics_of(self, role: str) -> str:
        return {
            "imu": self.topics.imu,
            "odometer": self.topics.odometer,
            "mag": self.topics.mag,
            "markers": self.topics.markers,
        }[role]

    def _high_water(self) -> int | None:
        hw = [s.high_water() for s in self.states.values() if s.role != "markers"]
        hw = [h for h in hw if h is not None]
        return max(hw) if hw else None

    def _lowest_buffered(self) -> int | None:
        lows = [int(p.ns.min()) for s in self.states.values() for p in s.buffer if len(p)]
        lows += [
            int(s.pending.ns.min())
            for s in self.states.values()
            if s.pending is not None and len(s.pending)
        ]
        return min(lows) if lows else None

    def _emit(self, upto: int | None) -> SensorLog:
        parts = {s.role: s.emit(upto) for s in self.states.values()}
        imu, odo, mag, mk = parts["imu"], parts["odometer"], parts["mag"], parts["markers"]
        return SensorLog(
            imu=ImuSamples(ns_to_sec(imu.ns), imu.values["gyro"], imu.values["accel"])
            if len(imu)
            else empty_imu(),
            odometer=OdometerSamples(ns_to_sec(odo.ns), odo.values["distance"], odo.values["speed"])
            if len(odo)
            else empty_odometer(),
            mag=MagSamples(ns_to_sec(mag.ns), mag.values["field"]) if len(mag) else empty_mag(),
            markers=list(mk.values["marker"]),
        )

    def chunks(self, chunk_seconds: float, lag_seconds: float) -> Iterator[SensorLog]:
        streaming = math.isfinite(chunk_seconds)
        if streaming and chunk_seconds <= 0:
            raise ValueError("chunk_seconds must be positive")
        chunk_ns = sec_to_ns_scalar(chunk_seconds) if streaming else 0
        lag_ns = sec_to_ns_scalar(lag_seconds)
        next_b: int | None = None
        for batch, roles in self._batches():
            self._ingest_batch(batch, roles)
            if not streaming:
                continue
            hw = self._high_water()
            if hw is None:
                continue
            if next_b is None:
                low = self._lowest_buffered()
                if low is None:
                    continue
                next_b = (low // chunk_ns + 1) * chunk_ns
            while next_b is not None and hw >= next_b + lag_ns:
                log = self._emit(next_b)
                if _log_len(log):
                    yield log
                low = self._lowest_buffered()
                # next chunk: the one holding the oldest buffered sample (skips empty stretches)
                next_b = (
                    None
                    if low is None
                    else max(next_b + chunk_ns, (low // chunk_ns + 1) * chunk_ns)
                )
        for s in self.states.values():
            s.flush_pending()
        if streaming:
            # hand out what is left, still one time chunk at a time
            while (low := self._lowest_buffered()) is not None:
                log = self._emit((low // chunk_ns + 1) * chunk_ns)
                if _log_len(log):
                    yield log
        else:
            yield self._emit(None)
        self._finish()

    def _finish(self) -> None:
        r = self.report
        if self.messages_read == 0 and r.truncated and not any(r.counts.values()):
            raise BagError(f"{self.path}: truncated or corrupt before any message could be read")
        for s in self.states.values():
            if s.seen == 0 and not r.skipped_by_topic.get(s.topic):
                r.warn(f"{s.topic}: no messages in the bag{_MISSING_HINT[s.role]}")
        for topic, reasons in r.skipped_by_topic.items():
            for reason, n in reasons.items():
                r.warn(f"{topic}: dropped {n} message(s): {_REASON_TEXT.get(reason, reason)}")


_REASON_TEXT = {
    SKIP_NAN: "NaN or infinite values",
    SKIP_BAD_CDR: "payload could not be deserialized",
    SKIP_NON_MONOTONIC: f"stamp more than {REORDER_WINDOW_S} s older than the newest one",
    SKIP_DUPLICATE: "repeated stamp",
    SKIP_TIME_JUMP: f"isolated stamp more than {TIME_JUMP_S} s ahead of its neighbours",
    SKIP_LATE: "arrived after its time chunk was handed out (streaming)",
    SKIP_UNKNOWN_TYPE: "unexpected message type",
    SKIP_CORRUPT_CHUNK: "in a corrupt chunk",
}


def _log_len(log: SensorLog) -> int:
    return len(log.imu) + len(log.odometer) + len(log.mag) + len(log.markers)


# ----------------------------------------------------------------------------- public API


def read_bag(
    path: str | os.PathLike[str],
    topics: TopicNames = DEFAULT_TOPICS,
    *,
    workers: int | None = None,
) -> tuple[SensorLog, BagReport]:
    """Read a whole bag (single .mcap or rosbag2 directory) into a SensorLog.

    Every topic comes out strictly increasing in header stamp (seconds), vectors in their
    message frame (imu_link), markers sorted by time. Problems are counted and described in
    the returned BagReport; a file that cannot be read at all raises BagError.

    ``workers``: threads that decompress and check the zstd chunks a few ahead of the
    decoding (:func:`read_workers`; default one on two cores or more); everything else runs in
    this thread in file order, so the log and the report are exactly those of ``workers=0``.
    """
    reader = _BagReader(path, topics, None, workers)
    logs = list(reader.chunks(math.inf, 0.0))
    return (logs[0] if logs else SensorLog()), reader.report


def iter_bag(
    path: str | os.PathLike[str],
    topics: TopicNames = DEFAULT_TOPICS,
    chunk_seconds: float = 60.0,
    report: BagReport | None = None,
    *,
    lag_seconds: float = EMIT_LAG_S,
    workers: int | None = None,
) -> Iterator[SensorLog]:
    """Stream a bag as consecutive time chunks of about ``chunk_seconds`` of header-stamp time.

    Memory stays bounded: the MCAP chunks being unpacked (at most two per worker thread, see
    :func:`read_bag` for ``workers``, plus one) plus ``lag_seconds`` + one chunk of decoded
    samples. Chunk k holds the samples with stamps in [b_k, b_k+1) (b_k are multiples of
    chunk_seconds; empty chunks are not yielded); each topic is strictly increasing within and
    across chunks; markers are in the chunk containing their stamp. Pass a BagReport as
    ``report`` to read the counts and warnings after the iteration (the generator's return value
    is the same report). BagError for an unreadable bag is raised by this call.
    """
    reader = _BagReader(path, topics, report, workers)

    def gen() -> Iterator[SensorLog]:
        yield from reader.chunks(float(chunk_seconds), float(lag_seconds))
        return reader.report

    return gen()


def concat_logs(logs: Sequence[SensorLog]) -> SensorLog:
    """Concatenate time chunks (e.g. from iter_bag) into one SensorLog."""
    logs = list(logs)
    if not logs:
        return SensorLog()
    return SensorLog(
        imu=ImuSamples(
            np.concatenate([x.imu.t for x in logs]),
            np.concatenate([x.imu.gyro for x in logs]),
            np.concatenate([x.imu.accel for x in logs]),
        ),
        odometer=OdometerSamples(
            np.concatenate([x.odometer.t for x in logs]),
            np.concatenate([x.odometer.distance for x in logs]),
            np.concatenate([x.odometer.speed for x in logs]),
        ),
        mag=MagSamples(
            np.concatenate([x.mag.t for x in logs]), np.concatenate([x.mag.field for x in logs])
        ),
        markers=sorted((m for x in logs for m in x.markers), key=lambda m: m.t),
    )


# ----------------------------------------------------------------------------- info


@dataclass
class TopicInfo:
    """One topic of a bag: type, message count and the first/last header stamp (s; the log
    time for types without a header)."""

    topic: str
    msgtype: str
    count: int
    start: float | None = None
    end: float | None = None


@dataclass
class BagInfo:
    """Cheap facts about a bag. ``indexed``: taken from the MCAP summaries (else by a scan);
    stamps then come from the first and last chunk of each topic."""

    path: str
    files: list[str]
    topics: dict[str, TopicInfo]
    message_count: int
    indexed: bool
    truncated: bool = False
    warnings: list[str] = field(default_factory=list)

    @property
    def start(self) -> float | None:
        v = [t.start for t in self.topics.values() if t.start is not None]
        return min(v) if v else None

    @property
    def end(self) -> float | None:
        v = [t.end for t in self.topics.values() if t.end is not None]
        return max(v) if v else None

    @property
    def duration(self) -> float:
        return (self.end - self.start) if self.start is not None and self.end is not None else 0.0


_HEADER_FIRST = "std_msgs/Header header"


def _has_header(schema_data: bytes, typename: str) -> bool:
    if typename in ROLE_TYPES.values() or typename in (
        "nav_msgs/msg/Path",
        "diagnostic_msgs/msg/DiagnosticArray",
    ):
        return True
    for line in schema_data.decode("utf-8", "replace").splitlines():
        s = line.split("#", 1)[0].strip()
        if s:
            return " ".join(s.split()[:2]) in (_HEADER_FIRST, "std_msgs/msg/Header header")
    return False


def _stamps(batch: MessageBatch, sel: NDArray[np.int64], header: bool) -> NDArray[np.int64]:
    if not header:
        return batch.log_time[sel]
    starts = batch.payload_start[sel]
    ok = batch.size[sel] >= 12
    starts = np.where(ok, starts, 0)
    raw = batch.buf[(starts + 4)[:, None] + np.arange(8)]
    sec = raw[:, :4].copy().view("<i4").reshape(-1).astype(np.int64)
    nsec = raw[:, 4:].copy().view("<u4").reshape(-1).astype(np.int64)
    return np.where(ok, sec * NS_PER_S + nsec, batch.log_time[sel])


def bag_info(path: str | os.PathLike[str]) -> BagInfo:
    """Per-topic message counts, types and first/last header stamps, cheaply: from the MCAP
    summary (counts) and the first and last chunk of each topic (stamps) when the files are
    indexed, otherwise by scanning (slower, still vectorized)."""
    files = bag_files(path)
    topics: dict[str, TopicInfo] = {}
    warnings: list[str] = []
    indexed = True
    truncated = False
    total = 0

    def add(topic: str, typename: str, n: int, lo: int | None, hi: int | None) -> None:
        ti = topics.setdefault(topic, TopicInfo(topic, typename, 0))
        ti.count += n
        if lo is not None:
            s = float(ns_to_sec(lo))
            ti.start = s if ti.start is None else min(ti.start, s)
        if hi is not None:
            e = float(ns_to_sec(hi))
            ti.end = e if ti.end is None else max(ti.end, e)

    for f in files:
        if not f.is_file():
            warnings.append(f"{f}: missing")
            truncated = True
            continue
        try:
            summ = read_summary(f)
        except OSError as exc:
            raise BagError(f"{f}: cannot read ({exc.strerror or exc})") from None
        if summ is not None and summ.chunk_indexes:
            cache: dict[int, MessageBatch | None] = {}
            for cid, ch in summ.channels.items():
                sch = summ.schemas.get(ch.schema_id)
                typename = normalize_type(sch.name) if sch else ""
                header = _has_header(sch.data if sch else b"", typename)
                cis = [ci for ci in summ.chunk_indexes if cid in ci.message_index_offsets]
                n = 0
                if summ.channel_message_counts is not None:
                    n = summ.channel_message_counts.get(cid, 0)
                lo = hi = None
                if cis:
                    first = min(cis, key=lambda c: c.message_start_time)
                    last = max(cis, key=lambda c: c.message_end_time)
                    for ci, want in ((first, "lo"), (last, "hi")):
                        key = ci.chunk_start_offset
                        if key not in cache:
                            cache[key] = chunk_messages(f, ci)
                        b = cache[key]
                        if b is None:
                            continue
                        sel = np.flatnonzero(b.channel == cid)
                        if not len(sel):
                            continue
                        st = _stamps(b, sel, header)
                        if want == "lo":
                            lo = int(st.min())
                        else:
                            hi = int(st.max())
                    if summ.channel_message_counts is None:
                        n = 0
                        for ci in cis:
                            key = ci.chunk_start_offset
                            if key not in cache:
                                cache[key] = chunk_messages(f, ci)
                            b = cache[key]
                            n += 0 if b is None else int((b.channel == cid).sum())
                add(ch.topic, typename, n, lo, hi)
                total += n
            continue
        indexed = False
        try:
            sc = McapScanner(f, warnings.append)
        except McapFormatError as exc:
            raise BagError(f"{f}: {exc}") from None
        for b in sc.batches():
            for cid in np.unique(b.channel).tolist():
                ch = sc.channels.get(cid)
                if ch is None:
                    continue
                sch = sc.schemas.get(ch.schema_id)
                typename = normalize_type(sch.name) if sch else ""
                sel = np.flatnonzero(b.channel == cid)
                st = _stamps(b, sel, _has_header(sch.data if sch else b"", typename))
                add(ch.topic, typename, len(sel), int(st.min()), int(st.max()))
                total += len(sel)
        truncated |= sc.truncated
    return BagInfo(str(path), [str(f) for f in files], topics, total, indexed, truncated, warnings)


def bag_time_range(
    path: str | os.PathLike[str], topics: Sequence[str] | None = None
) -> tuple[float, float] | None:
    """(first, last) header stamp in seconds over ``topics`` (default all), or None if empty."""
    info = bag_info(path)
    sel = [t for name, t in info.topics.items() if topics is None or name in topics]
    starts = [t.start for t in sel if t.start is not None]
    ends = [t.end for t in sel if t.end is not None]
    if not starts or not ends:
        return None
    return min(starts), max(ends)


_COVARIANCES = ("angular_velocity_covariance", "linear_acceleration_covariance")


def _declared_noise(
    buf: NDArray[np.uint8], starts: NDArray[np.int64], sizes: NDArray[np.int64]
) -> dict[str, list[float]]:
    """The variance diagonals of the first Imu message of (starts, sizes) in buf, or {}."""
    values, ok = cdr.decode_batch(cdr.IMU, buf, starts[:1], sizes[:1], _COVARIANCES)
    if not ok.all():
        return {}
    gv, av = (np.asarray(values[n], dtype=float)[0, [0, 4, 8]] for n in _COVARIANCES)
    return {"gyro_variance": gv.tolist(), "accel_variance": av.tolist()}


def declared_imu_noise(path: str | os.PathLike[str], topic: str) -> dict[str, Any]:
    """The per-sample variances (diagonals, (rad/s)^2 and (m/s^2)^2) the bag's first Imu
    message on ``topic`` declares, or {} (no message, or one that does not decode): what the
    IMU model of imu_grade auto falls back on (imu_model.choose)."""
    from mcap.reader import make_reader

    for f in bag_files(path):
        try:
            with open(f, "rb") as fh:
                for _s, _c, message in make_reader(fh).iter_messages(topics=[topic]):
                    buf = np.frombuffer(message.data, dtype=np.uint8)
                    return _declared_noise(buf, np.array([0]), np.array([len(buf)]))
        except Exception:  # an unreadable first message says nothing about the noise
            return {}
    return {}
