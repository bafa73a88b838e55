"""Vectorized CDR codec: bit-exact against rosbags' typestore (de)serialization."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pipe_nav_core.io import cdr, rosmsg
from pipe_nav_core.io.rosmsg import jazzy_typestore
from pipe_nav_core.io.stamps import sec_to_ns
from rosbags.serde import SerdeError

TS = jazzy_typestore()
T = TS.types
RNG = np.random.default_rng(42)


def _time():
    return T["builtin_interfaces/msg/Time"](
        sec=int(RNG.integers(-(2**31), 2**31 - 1)), nanosec=int(RNG.integers(0, 10**9))
    )


def _hdr(frame: str):
    return T["std_msgs/msg/Header"](stamp=_time(), frame_id=frame)


def _v3():
    return T["geometry_msgs/msg/Vector3"](*RNG.normal(size=3).tolist())


def _frame(k: int) -> str:
    return "".join(chr(97 + (i % 26)) for i in range(k))


def _imu(k: int):
    return T["sensor_msgs/msg/Imu"](
        header=_hdr(_frame(k)),
        orientation=T["geometry_msgs/msg/Quaternion"](*RNG.normal(size=4).tolist()),
        orientation_covariance=RNG.normal(size=9),
        angular_velocity=_v3(),
        angular_velocity_covariance=RNG.normal(size=9),
        linear_acceleration=_v3(),
        linear_acceleration_covariance=RNG.normal(size=9),
    )


def _odom(k: int):
    p = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](*RNG.normal(size=3).tolist()),
        orientation=T["geometry_msgs/msg/Quaternion"](*RNG.normal(size=4).tolist()),
    )
    tw = T["geometry_msgs/msg/Twist"](linear=_v3(), angular=_v3())
    return T["nav_msgs/msg/Odometry"](
        header=_hdr(_frame(k)),
        child_frame_id=_frame((k * 7) % 13),
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=RNG.normal(size=36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=tw, covariance=RNG.normal(size=36)),
    )


def _mag(k: int):
    return T["sensor_msgs/msg/MagneticField"](
        header=_hdr(_frame(k)), magnetic_field=_v3(), magnetic_field_covariance=RNG.normal(size=9)
    )


def _fix(k: int):
    return T["sensor_msgs/msg/NavSatFix"](
        header=_hdr(_frame(k)),
        status=T["sensor_msgs/msg/NavSatStatus"](
            status=int(RNG.integers(-2, 3)), service=int(RNG.integers(0, 16))
        ),
        latitude=float(RNG.uniform(-90, 90)),
        longitude=float(RNG.uniform(-180, 180)),
        altitude=float(RNG.normal() * 100),
        position_covariance=RNG.normal(size=9),
        position_covariance_type=int(RNG.integers(0, 4)),
    )


def _values(typename: str, m) -> dict[str, object]:
    """Flattened field values of a rosbags message, keyed like the cdr layouts."""
    h = {
        "sec": m.header.stamp.sec,
        "nanosec": m.header.stamp.nanosec,
        "frame_id": m.header.frame_id,
    }
    xyz = lambda v: [v.x, v.y, v.z]  # noqa: E731
    q = lambda v: [v.x, v.y, v.z, v.w]  # noqa: E731
    if typename == "sensor_msgs/msg/Imu":
        return h | {
            "orientation": q(m.orientation),
            "orientation_covariance": m.orientation_covariance,
            "angular_velocity": xyz(m.angular_velocity),
            "angular_velocity_covariance": m.angular_velocity_covariance,
            "linear_acceleration": xyz(m.linear_acceleration),
            "linear_acceleration_covariance": m.linear_acceleration_covariance,
        }
    if typename == "nav_msgs/msg/Odometry":
        return h | {
            "child_frame_id": m.child_frame_id,
            "position": xyz(m.pose.pose.position),
            "orientation": q(m.pose.pose.orientation),
            "pose_covariance": m.pose.covariance,
            "linear": xyz(m.twist.twist.linear),
            "angular": xyz(m.twist.twist.angular),
            "twist_covariance": m.twist.covariance,
        }
    if typename == "sensor_msgs/msg/MagneticField":
        return h | {
            "magnetic_field": xyz(m.magnetic_field),
            "magnetic_field_covariance": m.magnetic_field_covariance,
        }
    return h | {
        "status": m.status.status,
        "service": m.status.service,
        "latitude": m.latitude,
        "longitude": m.longitude,
        "altitude": m.altitude,
        "position_covariance": m.position_covariance,
        "position_covariance_type": m.position_covariance_type,
    }


CASES = [
    (cdr.IMU, _imu),
    (cdr.ODOMETRY, _odom),
    (cdr.MAGNETIC_FIELD, _mag),
    (cdr.NAVSATFIX, _fix),
]


@pytest.mark.parametrize(("layout", "make"), CASES, ids=lambda x: getattr(x, "typename", ""))
@pytest.mark.parametrize("lengths", ["mixed", "one"])
def test_decode_batch_matches_rosbags(layout, make, lengths):
    """Frame ids of 0..39 characters, or all of 8 (the decoder's one-offset path)."""
    ks = range(40) if lengths == "mixed" else [8] * 40
    msgs = [make(k) for k in ks for _ in range(2)]
    raws = [bytes(TS.serialize_cdr(m, layout.typename)) for m in msgs]
    # Put them in one buffer with odd gaps between them, as in an MCAP chunk.
    buf = bytearray(b"\xee" * 3)
    starts = []
    for r in raws:
        starts.append(len(buf))
        buf += r + b"\xff" * 31
    vals, ok = cdr.decode_batch(
        layout,
        np.frombuffer(bytes(buf), np.uint8),
        np.array(starts),
        np.array([len(r) for r in raws]),
    )
    assert ok.all()
    for i in range(len(msgs)):
        ref = TS.deserialize_cdr(raws[i], layout.typename)
        for name, want in _values(layout.typename, ref).items():
            got = vals[name][i]
            if isinstance(want, str):
                assert got == want, name
            elif isinstance(want, float) or np.asarray(want).dtype.kind == "f":
                # bit-exact, not just equal
                w = np.asarray(want, dtype="<f8").tobytes()
                assert np.asarray(got, dtype="<f8").tobytes() == w, name
            else:
                assert int(got) == int(want), name


@pytest.mark.parametrize(("layout", "make"), CASES, ids=lambda x: getattr(x, "typename", ""))
def test_encode_matches_rosbags_byte_for_byte(layout, make):
    for k in range(0, 40, 3):
        m = make(k)
        vals = _values(layout.typename, m)
        strings = {f: vals.pop(f) for f in layout.string_fields}
        mine = cdr.encode_one(layout, vals, strings)
        assert mine == bytes(TS.serialize_cdr(m, layout.typename))


def test_encode_batch_rows_equal_single_messages():
    n = 50
    gyro = RNG.normal(size=(n, 3))
    acc = RNG.normal(size=(n, 3))
    ns = sec_to_ns(1000.0 + np.arange(n) / 200.0)
    sec = ns // 10**9
    rec = cdr.encode_batch(
        cdr.IMU,
        n,
        {
            "sec": sec,
            "nanosec": ns - sec * 10**9,
            "angular_velocity": gyro,
            "linear_acceleration": acc,
        },
        {"frame_id": "imu_link"},
    )
    types = rosmsg.rosbags_types()
    for i in range(n):
        m = rosmsg.imu_to_msg(types, (1000.0 + i / 200.0), gyro[i], acc[i])
        m.orientation.w = 0.0
        m.orientation_covariance[0] = 0.0
        assert rec[i].tobytes() == bytes(TS.serialize_cdr(m, "sensor_msgs/msg/Imu"))


def test_decode_refuses_big_endian_and_short_payloads():
    m = _mag(5)
    le = bytes(TS.serialize_cdr(m, "sensor_msgs/msg/MagneticField"))
    be = bytes(TS.serialize_cdr(m, "sensor_msgs/msg/MagneticField", little_endian=False))
    short = le[:-8]
    garbage_len = bytearray(le)
    garbage_len[12:16] = (10**6).to_bytes(4, "little")  # absurd frame_id length
    buf = le + be + short + bytes(garbage_len)
    starts = np.cumsum([0, len(le), len(be), len(short)])
    sizes = np.array([len(le), len(be), len(short), len(garbage_len)])
    vals, ok = cdr.decode_batch(cdr.MAGNETIC_FIELD, np.frombuffer(buf, np.uint8), starts, sizes)
    assert ok.tolist() == [True, False, False, False]
    assert vals["magnetic_field"].shape == (1, 3)
    # among messages whose frame ids are all of one length, as in a field bag
    buf2 = le + be + le + short + le
    starts2 = np.cumsum([0, len(le), len(be), len(le), len(short)])
    sizes2 = np.array([len(le), len(be), len(le), len(short), len(le)])
    mixed = np.frombuffer(buf2, np.uint8)
    vals2, ok2 = cdr.decode_batch(cdr.MAGNETIC_FIELD, mixed, starts2, sizes2)
    assert ok2.tolist() == [True, False, True, False, True]
    assert (vals2["magnetic_field"] == vals["magnetic_field"][0]).all()
    # the big-endian one is still readable by the generic fallback
    ref = TS.deserialize_cdr(be, "sensor_msgs/msg/MagneticField")
    assert ref.magnetic_field.x == m.magnetic_field.x


def _same(got, want) -> bool:
    """A decoded value against rosbags' (floats bit for bit, strings and integers equal)."""
    if isinstance(want, str):
        return got == want
    if isinstance(want, float) or np.asarray(want).dtype.kind == "f":
        return np.asarray(got, "<f8").tobytes() == np.asarray(want, "<f8").tobytes()
    return int(got) == int(want)


_DAMAGE = st.sampled_from(["none", "none", "cut", "length", "big", "header", "byte"])


@settings(max_examples=60, deadline=None)
@given(
    case=st.sampled_from(CASES),
    plan=st.lists(st.tuples(st.integers(0, 12), _DAMAGE, st.integers(0, 10**6)), max_size=12),
)
def test_decode_batch_keeps_what_rosbags_reads_in_a_damaged_batch(case, plan):
    """Messages of mixed frame-id lengths (the compiled decoder's plan changes with them), some
    cut short, with an absurd string length, big-endian, a wrong header or a byte flipped:
    every undamaged one is decoded, and every one decoded equals rosbags' reading of its
    bytes where rosbags reads them (it refuses a frame id that lost its NUL or is not UTF-8,
    which the decoder keeps: the samples are good)."""
    layout, make = case
    buf = bytearray(b"\xee" * 5)
    starts, raws, intact = [], [], []
    for k, damage, r in plan:
        raw = bytearray(TS.serialize_cdr(make(k), layout.typename, little_endian=damage != "big"))
        if damage == "cut":
            raw = raw[: r % len(raw)]
        elif damage == "length":
            raw[12:16] = (len(raw) + 1 + r).to_bytes(4, "little")  # the frame id's length word
        elif damage == "header":
            raw[1] = 7
        elif damage == "byte":
            raw[r % len(raw)] ^= 0xFF
        starts.append(len(buf))
        raws.append(bytes(raw))
        intact.append(damage == "none")
        buf += raw + b"\xff" * (r % 9)
    vals, ok = cdr.decode_batch(
        layout,
        np.frombuffer(bytes(buf), np.uint8),
        np.array(starts, dtype=np.int64),
        np.array([len(r) for r in raws], dtype=np.int64),
    )
    assert ok.shape == (len(raws),)
    assert all(ok[i] for i in range(len(raws)) if intact[i])
    for row, i in enumerate(np.flatnonzero(ok)):
        try:
            msg = TS.deserialize_cdr(raws[i], layout.typename)
        except SerdeError:
            assert not intact[i]
            continue
        want = _values(layout.typename, msg)
        for name, w in want.items():
            assert _same(vals[name][row], w), (i, name)


@pytest.mark.parametrize("n", [0, 1, 2, 7])
@pytest.mark.parametrize("frame", ["map", "", "a_longer_frame"])
def test_encode_path_matches_rosbags(n, frame):
    types = rosmsg.rosbags_types()
    stamps = sec_to_ns(50.0 + np.arange(n) * 0.25)
    pos = RNG.normal(size=(n, 3)) * 100
    q = RNG.normal(size=(n, 4))
    poses = [
        types.PoseStamped(
            header=types.Header(stamp=rosmsg.ns_to_stamp(types, int(stamps[i])), frame_id=frame),
            pose=types.Pose(
                position=types.Point(*pos[i].tolist()), orientation=types.Quaternion(*q[i].tolist())
            ),
        )
        for i in range(n)
    ]
    msg = types.Path(
        header=types.Header(stamp=rosmsg.ns_to_stamp(types, 123456789012), frame_id=frame),
        poses=poses,
    )
    ref = bytes(TS.serialize_cdr(msg, "nav_msgs/msg/Path"))
    assert cdr.encode_path(123456789012, stamps, pos, q, frame) == ref


@pytest.mark.parametrize("n", [0, 1, 3])
@pytest.mark.parametrize("frame", ["map", "", "a_longer_frame"])
def test_encode_pose_array_matches_rosbags(n, frame):
    types = rosmsg.rosbags_types()
    pos = RNG.normal(size=(n, 3)) * 100
    q = RNG.normal(size=(n, 4))
    msg = types.PoseArray(
        header=types.Header(stamp=rosmsg.ns_to_stamp(types, -1_700_000_000), frame_id=frame),
        poses=[
            types.Pose(position=types.Point(*p.tolist()), orientation=types.Quaternion(*r.tolist()))
            for p, r in zip(pos, q, strict=True)
        ],
    )
    ref = bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/PoseArray"))
    assert cdr.encode_pose_array(-1_700_000_000, pos, q, frame) == ref


def test_stored_message_definitions_are_jazzys():
    """io/msgdefs.py holds what rosbags' Jazzy typestore generates for every type we write."""
    from pipe_nav_core.io import topics
    from pipe_nav_core.io.msgdefs import DEFINITIONS, HASHES

    written = {topics.IMU_TYPE, topics.ODOMETRY_TYPE, topics.MAG_TYPE, topics.NAVSATFIX_TYPE,
               topics.PATH_TYPE, topics.POSE_ARRAY_TYPE}  # fmt: skip
    assert set(DEFINITIONS) == set(HASHES) == written
    for name in written:
        assert DEFINITIONS[name] == TS.generate_msgdef(name, ros_version=2)[0], name
        assert HASHES[name] == TS.hash_rihs01(name), name


@pytest.mark.parametrize("name", ["agm_1", "", "a marker with a long name"])
def test_marker_navsatfix_matches_rosbags(name):
    """The sensor bag's marker passages, written by io/cdr, are rosmsg.marker_to_msg's message
    as rosbags serializes it."""
    import math

    from pipe_nav_core.io import bagwrite
    from pipe_nav_core.io.rosmsg import COVARIANCE_TYPE_DIAGONAL_KNOWN
    from pipe_nav_core.types import Marker

    m = Marker(name, 123.456789, math.radians(36.06), math.radians(103.83), 1520.25,
               (0.02, 0.025, 0.03))  # fmt: skip
    ns = int(sec_to_ns(np.array([m.t]))[0])
    ref = bytes(TS.serialize_cdr(rosmsg.marker_to_msg(rosmsg.rosbags_types(), m),
                                 "sensor_msgs/msg/NavSatFix"))  # fmt: skip
    cov = np.diag(np.asarray(m.sigma_enu) ** 2).reshape(9)
    assert bagwrite._navsatfix(ns, name, m.lat, m.lon, m.alt, cov,
                               COVARIANCE_TYPE_DIAGONAL_KNOWN) == ref  # fmt: skip
