"""Decoding the messages of one sensor role from an MCAP batch into samples (:class:`Pieces`).

The vectorized CDR decoder (:mod:`.cdr`) reads the well-formed messages in bulk; the messages it
refuses go through the generic rosbags deserializer (:func:`_fallback`), so an odd but valid
payload (e.g. a long frame_id) still counts, and only what neither can read is skipped
(``bad_cdr``). Samples with a NaN or infinite value are dropped (``nan``). Stamps are the header
stamps in integer ns; vectors stay in the message frame (imu_link): gyro rad/s, accel m/s^2,
odometer distance m and speed m/s, magnetic field T; markers become :class:`Marker` objects
through the same conversion as live messages (:func:`.rosmsg.marker_from_msg`, via
:class:`_NavSatView`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.io import cdr
from pipe_nav_core.io.mcapread import MessageBatch
from pipe_nav_core.io.rosmsg import (
    imu_from_msg,
    jazzy_typestore,
    mag_from_msg,
    marker_from_msg,
    wheel_from_msg,
)
from pipe_nav_core.io.stamps import NS_PER_S
from pipe_nav_core.io.topics import ROLE_TYPES, SKIP_BAD_CDR, SKIP_NAN, BagReport
from pipe_nav_core.types import Marker

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


@dataclass
class Pieces:
    """Decoded samples of one topic in arrival order: stamps (ns) and value arrays; ``log``:
    each message's log time in the bag (ns; when the recorder received it), where known."""

    ns: NDArray[np.int64]
    values: dict[str, NDArray]
    log: NDArray[np.int64] | None = None

    def take(self, idx: NDArray | slice) -> Pieces:
        """The samples at ``idx`` (indices or a mask, in that order; or a slice: views)."""
        log = None if self.log is None else self.log[idx]
        return Pieces(self.ns[idx], {k: v[idx] for k, v in self.values.items()}, log)

    def __len__(self) -> int:
        return len(self.ns)

    @staticmethod
    def concat(parts: Sequence[Pieces], keys: Sequence[str]) -> Pieces:
        """The parts one after the other (the part itself when there is one); their log
        times where every part has them."""
        if len(parts) == 1:
            return parts[0]
        logs = [p.log for p in parts]
        return Pieces(
            np.concatenate([p.ns for p in parts]),
            {k: np.concatenate([p.values[k] for p in parts]) for k in keys},
            None if any(x is None for x in logs) else np.concatenate(logs),  # type: ignore[arg-type]
        )


# The value columns of each role: gyro rad/s and accel m/s^2 (N, 3), distance m and speed m/s
# (N,), field T (N, 3), marker Marker objects (N,).
VALUE_KEYS = {
    "imu": ("gyro", "accel"),
    "odometer": ("distance", "speed"),
    "mag": ("field",),
    "markers": ("marker",),
}


def empty_pieces(role: str) -> Pieces:
    """No samples of ``role``, with its columns in their shapes."""
    shapes = {"gyro": (0, 3), "accel": (0, 3), "distance": (0,), "speed": (0,), "field": (0, 3)}
    vals: dict[str, NDArray] = {}
    for k in VALUE_KEYS[role]:
        vals[k] = np.empty(0, dtype=object) if k == "marker" else np.zeros(shapes[k])
    return Pieces(np.zeros(0, dtype=np.int64), vals, np.zeros(0, dtype=np.int64))


def decode_role(
    role: str, batch: MessageBatch, sel: NDArray[np.int64], topic: str, report: BagReport
) -> Pieces:
    """Decode the messages ``sel`` of a batch for a role; returns the finite samples in file
    order. The first IMU message that decodes also gives ``report.imu_noise_declared`` (what
    the IMU model falls back on without a static span)."""
    starts = batch.payload_start[sel]
    sizes = batch.size[sel]
    vals, ok = cdr.decode_batch(_LAYOUT[role], batch.buf, starts, sizes, _FIELDS[role])
    good = np.flatnonzero(ok)
    if role == "imu" and len(good) and not report.imu_noise_declared:
        report.imu_noise_declared = declared_noise(batch.buf, starts[good[:1]], sizes[good[:1]])
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
        return empty_pieces(role)
    keys = VALUE_KEYS[role]
    pos = np.concatenate(pos_parts)
    p = Pieces(
        np.concatenate(ns_parts),
        {k: np.concatenate([v[k] for v in val_parts]) for k in keys},
        batch.log_time[sel[pos]],
    )
    if len(ns_parts) > 1:
        p = p.take(np.argsort(pos, kind="stable"))
    finite = _finite(role, p)
    if not finite.all():
        report.add_skipped(topic, SKIP_NAN, int((~finite).sum()))
        p = p.take(np.flatnonzero(finite))
    return p


def _role_values(role: str, vals: dict[str, object]) -> dict[str, NDArray]:
    """The role's value columns from the decoded CDR fields."""
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
    """Marker i of the decoded NavSatFix columns, converted exactly as a live message."""
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
    cols: dict[str, list] = {k: [] for k in VALUE_KEYS[role]}
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


def _finite(role: str, p: Pieces) -> NDArray[np.bool_]:
    """Per sample: every value (and a marker's time, position and sigmas) is finite."""
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


_COVARIANCES = ("angular_velocity_covariance", "linear_acceleration_covariance")


def declared_noise(
    buf: NDArray[np.uint8], starts: NDArray[np.int64], sizes: NDArray[np.int64]
) -> dict[str, list[float]]:
    """The variance diagonals of the first Imu message of (starts, sizes) in buf, or {}."""
    values, ok = cdr.decode_batch(cdr.IMU, buf, starts[:1], sizes[:1], _COVARIANCES)
    if not ok.all():
        return {}
    gv, av = (np.asarray(values[n], dtype=float)[0, [0, 4, 8]] for n in _COVARIANCES)
    return {"gyro_variance": gv.tolist(), "accel_variance": av.tolist()}
