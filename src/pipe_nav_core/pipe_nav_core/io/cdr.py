"""Vectorized CDR decoding and encoding of the fixed-layout sensor messages.

ROS 2 serializes messages as CDR (XCDR1): a 4-byte encapsulation header (``00 01 00 00`` for
little-endian) followed by the fields in declaration order, each primitive aligned to its own
size (at most 8) relative to the first byte after the header; a string is a uint32 length that
counts the terminating NUL, then the bytes and the NUL. sensor_msgs/Imu, nav_msgs/Odometry,
sensor_msgs/MagneticField and sensor_msgs/NavSatFix are fixed layouts except for their frame id
strings, so the offset of every field is a small arithmetic function of the string lengths.

Decoding walks thousands of messages of a chunk buffer in one compiled call
(:mod:`.cdr_decode`; no Python object per message); encoding builds a numpy structured array
whose rows are the serialized messages (optionally preceded by a fixed record prefix, used by
the MCAP writer for the Message record header). Messages that do not fit (big-endian, odd
lengths) are reported so that the caller can fall back to a generic deserializer.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.io.cdr_decode import KIND_CODES, decode_k

_SIZE = {"i1": 1, "u1": 1, "u2": 2, "i4": 4, "u4": 4, "f8": 8}
_DTYPE = {"i1": "<i1", "u1": "<u1", "u2": "<u2", "i4": "<i4", "u4": "<u4", "f8": "<f8"}
ENCAPSULATION_LE = bytes([0, 1, 0, 0])


@dataclass(frozen=True)
class Field:
    """One flattened field: kind in {'i1','u1','u2','i4','u4','f8','str'}; count for arrays."""

    name: str
    kind: str
    count: int = 1


@dataclass(frozen=True)
class MessageLayout:
    """Flattened CDR layout of a message type (strings may only be at the top level)."""

    typename: str
    fields: tuple[Field, ...]

    @property
    def string_fields(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields if f.kind == "str")

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(name)


_HEADER = (Field("sec", "i4"), Field("nanosec", "u4"), Field("frame_id", "str"))

IMU = MessageLayout(
    "sensor_msgs/msg/Imu",
    _HEADER
    + (
        Field("orientation", "f8", 4),
        Field("orientation_covariance", "f8", 9),
        Field("angular_velocity", "f8", 3),
        Field("angular_velocity_covariance", "f8", 9),
        Field("linear_acceleration", "f8", 3),
        Field("linear_acceleration_covariance", "f8", 9),
    ),
)

ODOMETRY = MessageLayout(
    "nav_msgs/msg/Odometry",
    _HEADER
    + (
        Field("child_frame_id", "str"),
        Field("position", "f8", 3),
        Field("orientation", "f8", 4),
        Field("pose_covariance", "f8", 36),
        Field("linear", "f8", 3),
        Field("angular", "f8", 3),
        Field("twist_covariance", "f8", 36),
    ),
)

MAGNETIC_FIELD = MessageLayout(
    "sensor_msgs/msg/MagneticField",
    _HEADER + (Field("magnetic_field", "f8", 3), Field("magnetic_field_covariance", "f8", 9)),
)

NAVSATFIX = MessageLayout(
    "sensor_msgs/msg/NavSatFix",
    _HEADER
    + (
        Field("status", "i1"),
        Field("service", "u2"),
        Field("latitude", "f8"),
        Field("longitude", "f8"),
        Field("altitude", "f8"),
        Field("position_covariance", "f8", 9),
        Field("position_covariance_type", "u1"),
    ),
)

LAYOUTS = {lay.typename: lay for lay in (IMU, ODOMETRY, MAGNETIC_FIELD, NAVSATFIX)}


def _align(pos, a: int):
    """Round pos (int or int64 array) up to a multiple of a (a power of two)."""
    return (pos + (a - 1)) & ~(a - 1)


def layout_offsets(
    layout: MessageLayout, string_lengths: Mapping[str, object]
) -> tuple[dict[str, object], object]:
    """Offsets of every field relative to the first byte after the encapsulation header.

    string_lengths: CDR length (bytes including the NUL) of each string field, int or int64
    array. For a string field the offset is that of its uint32 length word. Returns
    (offsets, end) where end is the serialized length without the 4-byte header.
    """
    pos: object = 0
    offsets: dict[str, object] = {}
    for f in layout.fields:
        if f.kind == "str":
            pos = _align(pos, 4)
            offsets[f.name] = pos
            pos = pos + 4 + string_lengths[f.name]
        else:
            pos = _align(pos, _SIZE[f.kind])
            offsets[f.name] = pos
            pos = pos + _SIZE[f.kind] * f.count
    return offsets, pos


def gather(buf: NDArray[np.uint8], pos: NDArray[np.int64], nbytes: int) -> NDArray[np.uint8]:
    """(n, nbytes) uint8 array of buf[pos[i] : pos[i] + nbytes]: the items ``pos`` of a view
    of buf as ``nbytes``-byte void items starting at every byte (one index and one copy of
    nbytes per message, not an index per byte: 10x faster; IndexError past the end). buf: a
    contiguous uint8 array."""
    items = np.ndarray(
        shape=(max(len(buf) - nbytes + 1, 0),),
        dtype=np.dtype((np.void, nbytes)),
        buffer=buf,
        strides=(1,),
    )
    return items[pos].view(np.uint8).reshape(len(pos), nbytes)


@dataclass(frozen=True)
class _Columns:
    """What :func:`.cdr_decode.decode_k` is told for some fields of a layout: per field of the
    layout its kind code, count and column (-1: not wanted); the widths of the two matrices;
    per wanted name (matrix "f" or "i", first column, count)."""

    kinds: NDArray[np.int64]
    counts: NDArray[np.int64]
    cols: NDArray[np.int64]
    n_floats: int
    n_ints: int
    where: dict[str, tuple[str, int, int]]


@lru_cache(maxsize=64)
def _columns(layout: MessageLayout, names: tuple[str, ...]) -> _Columns:
    cols, where = [], {}
    nf = ni = 0
    for f in layout.fields:
        if f.name not in names:
            cols.append(-1)
        elif f.kind == "f8":
            cols.append(nf)
            where[f.name] = ("f", nf, f.count)
            nf += f.count
        else:
            cols.append(ni)
            where[f.name] = ("i", ni, f.count)
            ni += 2 if f.kind == "str" else f.count
    return _Columns(
        np.array([KIND_CODES[f.kind] for f in layout.fields], dtype=np.int64),
        np.array([f.count for f in layout.fields], dtype=np.int64),
        np.array(cols, dtype=np.int64),
        nf,
        ni,
        where,
    )


def decode_batch(
    layout: MessageLayout,
    buf: NDArray[np.uint8],
    starts: NDArray[np.int64],
    sizes: NDArray[np.int64],
    fields: Sequence[str] | None = None,
) -> tuple[dict[str, object], NDArray[np.bool_]]:
    """Decode many CDR messages of one type that lie in ``buf`` (compiled, without the GIL:
    :func:`.cdr_decode.decode_k`).

    buf: uint8 array holding the messages; starts, sizes: payload offset (at the encapsulation
    header) and payload length of each message. fields: the field names to decode (default: all;
    string fields come back as a list of ``str``).

    Returns (values, ok): ``ok`` flags the messages that were decoded (little-endian, long enough,
    sane string lengths); values[name] has one row per ok message, in input order: shape (k,)
    for scalars and (k, count) for arrays, C-contiguous, of the field's dtype. Messages that are
    not ok should go to a generic deserializer (big-endian) or be counted as bad.
    """
    names = tuple(f.name for f in layout.fields) if fields is None else tuple(fields)
    columns = _columns(layout, names)
    starts = np.ascontiguousarray(starts, dtype=np.int64)
    sizes = np.ascontiguousarray(sizes, dtype=np.int64)
    n = len(starts)
    view = np.ascontiguousarray(buf, dtype=np.uint8).view()
    view.flags.writeable = False  # one argument type for the compiled kernel, whatever buf is
    floats = np.empty((n, columns.n_floats))
    ints = np.empty((n, columns.n_ints), dtype=np.int64)
    ok = np.empty(n, dtype=np.bool_)
    k = decode_k(view, starts, sizes, columns.kinds, columns.counts, columns.cols, floats, ints, ok)
    out: dict[str, object] = {}
    for name in names:
        kind = layout.field(name).kind
        matrix, c, count = columns.where[name]
        if kind == "str":
            out[name] = [
                view[p : p + m].tobytes().decode("utf-8", "replace")
                for p, m in ints[:k, c : c + 2].tolist()
            ]
            continue
        vals = (floats if matrix == "f" else ints)[:k, c : c + count]
        vals = vals.astype(_DTYPE[kind])  # a C-contiguous copy
        out[name] = vals.reshape(k) if count == 1 else vals
    return out, ok


def record_dtype(
    layout: MessageLayout, strings: Mapping[str, str], prefix: int = 0
) -> tuple[np.dtype, int]:
    """Structured dtype of one serialized message with constant strings.

    The record is ``prefix`` bytes (field '_prefix', left for the caller), the 4-byte
    encapsulation header ('_encap') and the CDR body; string fields become '<name>__len' (uint32)
    and '<name>' (bytes incl. NUL). Padding bytes are zero when the array is created with
    np.zeros. Returns (dtype, payload_size) where payload_size excludes the prefix.
    """
    enc = {k: v.encode("utf-8") for k, v in strings.items()}
    lengths = {k: len(v) + 1 for k, v in enc.items()}
    offsets, end = layout_offsets(layout, lengths)
    names: list[str] = ["_encap"]
    formats: list[object] = [("u1", 4)]
    offs: list[int] = [prefix]
    if prefix:
        names.insert(0, "_prefix")
        formats.insert(0, ("u1", prefix))
        offs.insert(0, 0)
    for f in layout.fields:
        o = prefix + 4 + int(offsets[f.name])
        if f.kind == "str":
            names += [f"{f.name}__len", f.name]
            formats += ["<u4", f"S{lengths[f.name]}"]
            offs += [o, o + 4]
        else:
            names.append(f.name)
            formats.append(_DTYPE[f.kind] if f.count == 1 else (_DTYPE[f.kind], (f.count,)))
            offs.append(o)
    size = 4 + int(end)
    dt = np.dtype({"names": names, "formats": formats, "offsets": offs, "itemsize": prefix + size})
    return dt, size


def encode_batch(
    layout: MessageLayout,
    n: int,
    values: Mapping[str, object],
    strings: Mapping[str, str],
    prefix: int = 0,
) -> np.ndarray:
    """Serialize n messages whose string fields are the constants ``strings``.

    values: field name -> scalar or array broadcastable to (n,) / (n, count); fields not given
    are zero. Returns a structured array (see :func:`record_dtype`) whose raw bytes per row are
    ``prefix`` bytes (zero, for the caller to fill) followed by the CDR payload.
    """
    dt, _ = record_dtype(layout, strings, prefix)
    rec = np.zeros(n, dtype=dt)
    rec["_encap"] = np.frombuffer(ENCAPSULATION_LE, dtype=np.uint8)
    for name, s in strings.items():
        raw = s.encode("utf-8")
        rec[f"{name}__len"] = len(raw) + 1
        rec[name] = raw
    for name, v in values.items():
        rec[name] = v
    return rec


def encode_one(
    layout: MessageLayout, values: Mapping[str, object], strings: Mapping[str, str]
) -> bytes:
    """Serialize a single message (convenience wrapper of :func:`encode_batch`)."""
    return encode_batch(layout, 1, values, strings).tobytes()


def _put_header(
    body: NDArray[np.uint8], header_ns: int, raw: bytes, seq_len_at: int, n: int
) -> None:
    """Write a std_msgs/Header (stamp ``header_ns`` ns, frame id ``raw`` UTF-8) at the start of
    a CDR body, and the length n of the sequence that follows it at ``seq_len_at``."""
    sec, nsec = divmod(int(header_ns), 1_000_000_000)
    body[0:4] = np.frombuffer(np.int32(sec).tobytes(), np.uint8)
    body[4:8] = np.frombuffer(np.uint32(nsec).tobytes(), np.uint8)
    body[8:12] = np.frombuffer(np.uint32(len(raw) + 1).tobytes(), np.uint8)
    body[12 : 12 + len(raw)] = np.frombuffer(raw, np.uint8)
    body[seq_len_at : seq_len_at + 4] = np.frombuffer(np.uint32(n).tobytes(), np.uint8)


def encode_path(
    header_ns: int,
    stamps_ns: NDArray[np.int64],
    position: NDArray[np.float64],
    orientation: NDArray[np.float64],
    frame_id: str = "map",
) -> bytes:
    """Serialize a nav_msgs/Path whose header and every PoseStamped use ``frame_id``.

    header_ns: Path header stamp, ns; stamps_ns (N,): pose stamps, ns; position (N, 3) m;
    orientation (N, 4) [x, y, z, w]. The payload is built with numpy: after the first pose,
    every PoseStamped starts 8-aligned and so has the same size.
    """
    raw = frame_id.encode("utf-8")
    slen = len(raw) + 1
    n = len(stamps_ns)
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    # Path header: sec, nanosec, frame_id; then the sequence length.
    seq_len_at = _align(12 + slen, 4)
    p0 = seq_len_at + 4

    def pose_at(p: int) -> int:
        return _align(p + 12 + slen, 8)

    size0 = pose_at(p0) + 56 - p0
    step = _align(12 + slen, 8) + 56
    starts = np.empty(n, dtype=np.int64)
    if n:
        starts[0] = p0
        starts[1:] = p0 + size0 + step * np.arange(n - 1, dtype=np.int64)
    end = int(starts[-1]) + (size0 if n == 1 else step) if n else p0
    out = np.zeros(4 + end, dtype=np.uint8)
    out[:4] = np.frombuffer(ENCAPSULATION_LE, dtype=np.uint8)
    body = out[4:]

    def put(pos: NDArray[np.int64], arr: NDArray, dt: str) -> None:
        a = np.ascontiguousarray(arr, dtype=dt)
        nb = a.dtype.itemsize * (a.shape[1] if a.ndim == 2 else 1)
        body[pos[:, None] + np.arange(nb, dtype=np.int64)] = a.view(np.uint8).reshape(len(pos), nb)

    _put_header(body, header_ns, raw, seq_len_at, n)
    if n:
        sec = np.floor_divide(stamps_ns, 1_000_000_000)
        put(starts, sec, "<i4")
        put(starts + 4, stamps_ns - sec * 1_000_000_000, "<u4")
        put(starts + 8, np.full(n, slen), "<u4")
        if raw:
            body[(starts + 12)[:, None] + np.arange(len(raw))] = np.frombuffer(raw, np.uint8)
        pose = starts + 12 + slen
        pose = (pose + 7) & ~7
        put(pose, position, "<f8")
        put(pose + 24, orientation, "<f8")
    return out.tobytes()


def encode_pose_array(
    header_ns: int,
    position: NDArray[np.float64],
    orientation: NDArray[np.float64],
    frame_id: str = "map",
) -> bytes:
    """Serialize a geometry_msgs/PoseArray: header stamp ``header_ns`` (ns) and ``frame_id``,
    then one Pose per row of position (N, 3) m and orientation (N, 4) [x, y, z, w]. The
    poses are 8-aligned and 56 bytes each, so they follow one another without padding."""
    raw = frame_id.encode("utf-8")
    slen = len(raw) + 1
    pos = np.asarray(position, dtype="<f8").reshape(-1, 3)
    quat = np.asarray(orientation, dtype="<f8").reshape(-1, 4)
    n = len(pos)
    seq_len_at = _align(12 + slen, 4)
    first = _align(seq_len_at + 4, 8) if n else seq_len_at + 4
    body = np.zeros(first + 56 * n, dtype=np.uint8)
    _put_header(body, header_ns, raw, seq_len_at, n)
    body[first:] = np.hstack([pos, quat]).view(np.uint8).reshape(-1)
    return ENCAPSULATION_LE + body.tobytes()
