"""ekf_node's message handling (EkfCore) with rosbags' Jazzy message classes, no ROS needed:
a simulated run goes in as sensor messages, Odometry / datum / diagnostics come out."""

from __future__ import annotations

import math

import numpy as np
import pytest
from arrivals import in_turns
from pipe_nav_ros.ekf_core import (
    BURST_ALLOWANCE_S,
    BURST_FACTOR,
    ERROR,
    INPUT_TOPICS,
    JUMP_CONFIRM,
    OK,
    WARN,
    EkfCore,
    LatencyStats,
    covariance_problem,
    twist_covariance,
)

from pipe_nav_core import NavConfig, NavEstimate, rosmsg, simulate

TYPES = rosmsg.rosbags_types()
CROP_S = 75.0  # rest, the first two markers (10 s, 62 s) and some travel


@pytest.fixture(scope="module")
def run():
    return simulate("demo", 0)


@pytest.fixture(scope="module")
def config(run):
    return NavConfig.from_dict(run.scenario.estimator_settings())


def input_messages(run, t_end=CROP_S):
    """(stamp, role, message) of the run's first t_end seconds in stamp order."""
    return rosmsg.log_to_messages(TYPES, run.log, t_end)


def feed(core, messages, sent=False):
    """Every message into core (each accepted), with its stamp as the sender's timestamp when
    sent; the estimates and datums that come out, finish() included."""
    handlers = {
        "imu": core.on_imu,
        "odometer": core.on_odometer,
        "mag": core.on_mag,
        "markers": core.on_marker,
    }
    odometry, datums = [], []
    for t, role, msg in messages:
        assert handlers[role](msg, sent=float(t) if sent else None)
        out = core.poll()
        odometry += out.odometry
        if out.datum is not None:
            datums.append(out.datum)
    out = core.finish()
    return odometry + out.odometry, datums + ([out.datum] if out.datum is not None else [])


@pytest.fixture(scope="module")
def result(run, config):
    core = EkfCore(config, TYPES, map_frame="map", base_frame="base_link")
    odometry, datums = feed(core, input_messages(run))
    return core, odometry, datums


def test_odometry_messages_follow_the_truth(run, result):
    _, odometry, datums = result
    assert len(odometry) > 500
    ts = rosmsg.jazzy_typestore()
    truth, d = run.truth, run.datum
    enu_true = rosmsg.enu_of(d, truth.lat, truth.lon, truth.h)
    errors, stamps = [], []
    for msg in odometry:
        # a valid Jazzy nav_msgs/Odometry
        msg = ts.deserialize_cdr(
            ts.serialize_cdr(msg, "nav_msgs/msg/Odometry"), "nav_msgs/msg/Odometry"
        )
        assert msg.header.frame_id == "map" and msg.child_frame_id == "base_link"
        o = rosmsg.odometry_from_msg(msg)
        j = min(int(np.searchsorted(truth.t, o["t"])), len(truth.t) - 1)
        errors.append(np.linalg.norm(o["position"] - enu_true[j]))
        stamps.append(o["t"])
        cov = o["pose_cov"]
        assert np.allclose(cov, cov.T) and np.all(np.diag(cov) > 0)
        assert abs(np.linalg.norm(o["quat"]) - 1.0) < 1e-9
    # the heading comes from the markers: loose until the second one re-anchors it, then close
    errors, stamps = np.array(errors), np.array(stamps)
    anchored = stamps > run.log.markers[1].t + 1.0
    assert anchored.sum() > 50
    assert errors[anchored].max() < 2.0
    assert errors.max() < 100.0
    assert np.all(np.diff(stamps) > 0)
    # the datum (first marker, the launch trap) was published exactly once
    assert len(datums) == 1
    datum = rosmsg.datum_from_msg(datums[0])
    first = run.log.markers[0]
    assert (datum.lat, datum.lon, datum.alt) == pytest.approx((first.lat, first.lon, first.alt))


def test_twist_is_in_base_link(run, result):
    _, odometry, _ = result
    truth = run.truth
    moving = [m for m in odometry if m.twist.twist.linear.x > 1.0]
    assert len(moving) > 100
    for msg in moving[:200]:
        t = rosmsg.stamp_to_sec(msg.header.stamp)
        j = min(int(np.searchsorted(truth.t, t)), len(truth.t) - 1)
        speed = np.linalg.norm(truth.vel_n[j])
        assert msg.twist.twist.linear.x == pytest.approx(speed, abs=0.15)
        cov = np.asarray(msg.twist.covariance).reshape(6, 6)
        assert np.all(np.diag(cov) > 0)


def test_twist_covariance_rotates_into_the_body():
    q = np.array([0.0, 0.0, 0.0, 1.0])  # nose east: base_link x along map (ENU) x
    est = NavEstimate(
        t=0.0,
        lat=0.0,
        lon=0.0,
        h=0.0,
        vel_n=np.zeros(3),
        quat_nb=q,
        omega_b=np.zeros(3),
        cov_pose=np.eye(6),
        cov_vel_n=np.diag([4.0, 1.0, 0.25]),
        distance=0.0,
        status="moving",
    )
    cov = twist_covariance(est, 1e-6)
    # body x points east: the east variance becomes the forward one
    assert np.diag(cov)[:3] == pytest.approx([4.0, 1.0, 0.25])
    assert np.diag(cov)[3:] == pytest.approx([1e-6] * 3)


def test_diagnostics_message(result):
    core = EkfCore(NavConfig(), TYPES)
    first = core.diagnostics(12.5, now=100.0)
    status = first.status[0]
    assert status.level == OK and status.message == "waiting for data"
    assert status.name == "pipe_nav: ekf_node" and status.hardware_id == "pipe_nav"
    ts = rosmsg.jazzy_typestore()
    ts.serialize_cdr(first, "diagnostic_msgs/msg/DiagnosticArray")
    for k in range(100):
        core.on_imu(rosmsg.imu_to_msg(TYPES, k * 0.01, [0, 0, 0], [0, 0, 9.8]))
    values = {kv.key: kv.value for kv in core.diagnostics(13.5, now=101.0).status[0].values}
    assert float(values["imu.rate_hz"]) == pytest.approx(100.0)
    assert values["imu.received"] == "100" and values["datum_known"] == "no"
    assert "engine.state" in values and "engine.received_imu" in values
    # the IMU stopped: warning
    assert core.diagnostics(14.5, now=102.0).status[0].level == WARN


def test_diagnostics_warn_when_the_imu_grade_does_not_fit():
    """A consumer-MEMS run (drag180) on the industrial noise model (set explicitly: the default
    imu_grade "auto" would measure it): once the filter navigates, /diagnostics turns WARN and
    names the setting to check."""
    run = simulate("drag180", 1)
    core = EkfCore(NavConfig(imu_grade="industrial"), TYPES)
    core.diagnostics(0.0, now=0.0)
    handlers = {"imu": core.on_imu, "odometer": core.on_odometer, "mag": core.on_mag,
                "markers": core.on_marker}  # fmt: skip
    statuses = []
    for k, (_, role, msg) in enumerate(input_messages(run, t_end=60.0)):
        assert handlers[role](msg)
        core.poll()
        if k % 2000 == 1999:
            statuses.append(core.diagnostics(float(k), now=float(k)).status[0])
    assert statuses[0].level == OK  # aligning at rest: nothing to judge yet
    assert statuses[-1].level == WARN and "imu_grade" in statuses[-1].message


def test_diagnostics_warn_of_an_imu_on_a_clock_of_its_own(run, config):
    """The IMU stamped 0.3 s late: re-timed at the second marker (live_guard), and /diagnostics
    turns WARN naming it from then on."""
    from pipe_nav_core.sim.faults import imu_clock

    core = EkfCore(config, TYPES)
    handlers = {"imu": core.on_imu, "odometer": core.on_odometer, "mag": core.on_mag,
                "markers": core.on_marker}  # fmt: skip
    late = rosmsg.log_to_messages(TYPES, imu_clock(run.log, 0.3), CROP_S)
    statuses = []
    for k, (_, role, msg) in enumerate(sorted(late, key=lambda m: m[0])):
        assert handlers[role](msg)
        core.poll()
        if k % 2000 == 1999:
            statuses.append(core.diagnostics(float(k), now=float(k)).status[0])
    assert statuses[0].level == OK
    assert statuses[-1].level == WARN and statuses[-1].message.startswith("IMU clock: its stamps")
    values = {kv.key: kv.value for kv in statuses[-1].values}
    assert values["engine.imu_clock_retimed"] == "1" and values["engine.state"] == "navigating"


def test_malformed_messages_are_counted_and_survived(run, config):
    core = EkfCore(config, TYPES)
    good = input_messages(run, t_end=3.0)
    problems = []
    core.on_problem = lambda role, text: problems.append((role, text))
    core.on_imu(None)  # not a message at all
    core.on_imu(rosmsg.mag_to_msg(TYPES, 0.0, [1e-5, 0, 0]))  # wrong type
    bad_marker = rosmsg.marker_to_msg(TYPES, run.log.markers[0])
    bad_marker.position_covariance = np.zeros(4)  # wrong size
    assert not core.on_marker(bad_marker)
    nan_imu = rosmsg.imu_to_msg(TYPES, 0.5, [math.nan, 0, 0], [0, 0, 9.8])
    assert core.on_imu(nan_imu)  # reaches the engine, which counts and drops it
    assert core.nav.diagnostics()["dropped_nan_imu"] == 1
    odometry, _ = feed(core, good)
    c = core.counters
    assert c["imu"].malformed == 2 and c["markers"].malformed == 0
    assert c["markers"].faults["covariance"] == 1 and c["imu"].faults["nan"] == 1
    assert [text.split(":")[0] for _, text in problems] == [
        "malformed message skipped",
        "malformed message skipped",
        "covariance",
        "nan",
    ]
    assert core.diagnostics(1.0, now=0.0).status[0].level == WARN
    assert core.resets == 1


def test_engine_failure_is_reported_not_raised(config):
    core = EkfCore(config, TYPES)

    def broken():
        raise RuntimeError("boom")

    core.nav.poll = broken
    out = core.poll()
    assert out.odometry == [] and core.poll_errors == 1
    level, message, _ = core.health(now=0.0)
    assert level == ERROR and "engine failed" in message


def test_reset_and_finish(run, config):
    core = EkfCore(config, TYPES)
    messages = input_messages(run, t_end=15.0)
    _, datums = feed(core, messages)  # finish() at the end resets
    assert len(datums) == 1 and core.resets == 1
    assert core.nav.datum is None
    # a second run after the reset publishes its datum again, with a new config
    core.reset(
        config=NavConfig.from_dict({**run.scenario.estimator_settings(), "filter_rate_hz": 5.0})
    )
    assert core.config.filter_rate_hz == 5.0
    _, datums = feed(core, messages)
    assert len(datums) == 1


def test_on_message_dispatches_by_topic(run, config):
    core = EkfCore(config, TYPES)
    msg = rosmsg.imu_to_msg(TYPES, 0.0, [0, 0, 0], [0, 0, 9.8])
    assert core.on_message("/imu/data", msg)
    assert not core.on_message("/camera/image", msg)
    later = rosmsg.imu_to_msg(TYPES, 0.01, [0, 0, 0], [0, 0, 9.8])
    assert core.on_message("/pig/imu", later, topics={"imu": "/pig/imu"})
    assert core.counters["imu"].received == 2


# ------------------------------------------------------------------------------ faults


def clean_estimates(run, config, messages):
    core = EkfCore(config, TYPES)
    odometry, datums = feed(core, messages)
    return odometry, datums


def positions(odometry):
    return np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z]
                     for m in odometry])  # fmt: skip


def test_faulty_messages_are_named_dropped_and_leave_the_estimates_unchanged(run, config):
    """Malformed copies of real messages inserted into a run: each kind is counted under its
    name and reported WARN; what is dropped does not change one estimate (a far-future stamp
    does not poison the reorder buffer), and the estimates stay finite."""
    messages = input_messages(run, t_end=CROP_S)
    reference, _ = clean_estimates(run, config, messages)
    core = EkfCore(config, TYPES)
    core.diagnostics(0.0, now=0.0)
    first_marker = next(msg for _, role, msg in messages if role == "markers")
    odometry = []

    def bad_messages(t):
        def imu(stamp=t, gyro=(0.01, 0.0, 0.0), frame_id="imu_link"):
            return rosmsg.imu_to_msg(TYPES, stamp, gyro, [0, 0, 9.8], frame_id=frame_id)

        odo = rosmsg.wheel_to_msg(TYPES, t, 1.0, 1.0)
        odo.header.frame_id = "map"
        mag = rosmsg.mag_to_msg(TYPES, t + 30.0, [2e-5, 0, -4e-5])
        marker = rosmsg.marker_to_msg(TYPES, rosmsg.marker_from_msg(first_marker))
        marker.position_covariance = np.zeros(4)
        return [
            ("imu", imu(stamp=t + 1000.0)),  # far future
            ("imu", imu(stamp=t - 5.0)),  # past
            ("imu", imu(frame_id="odom")),
            ("imu", imu(frame_id="")),
            ("imu", imu(gyro=(math.nan, 0.0, 0.0))),
            ("odometer", odo),  # frame "map"
            ("mag", mag),  # 30 s ahead
            ("markers", marker),  # covariance of 4 elements
        ]

    handlers = {"imu": core.on_imu, "odometer": core.on_odometer, "mag": core.on_mag,
                "markers": core.on_marker}  # fmt: skip
    injected_at = {int(len(messages) * f) for f in (0.2, 0.5, 0.8)}
    for k, (t, role, msg) in enumerate(messages):
        if k in injected_at:
            for bad_role, bad in bad_messages(t):
                handlers[bad_role](bad)
        if role == "imu" and k % 50 == 0:  # a good sample with unusable covariances: kept
            msg.angular_velocity_covariance = np.full(9, -1.0)
        assert handlers[role](msg)
        odometry += core.poll().odometry
    status = core.diagnostics(1.0, now=1.0).status[0]
    odometry += core.finish().odometry

    f = {role: c.faults for role, c in core.counters.items()}
    assert f["imu"]["stamp_future"] == 3 and f["imu"]["stamp_past"] == 3
    assert f["imu"]["frame_id"] == 6 and f["imu"]["nan"] == 3
    assert f["imu"]["covariance"] == len(range(0, len(messages), 50)) - sum(
        1 for k in range(0, len(messages), 50) if messages[k][1] != "imu"
    )
    assert f["odometer"]["frame_id"] == 3 and f["mag"]["stamp_future"] == 3
    assert f["markers"]["covariance"] == 3 and f["imu"]["burst"] == 0
    values = {kv.key: kv.value for kv in status.values}
    for role in ("imu", "odometer", "mag", "markers"):
        for kind in (
            "nan",
            "frame_id",
            "stamp_future",
            "stamp_past",
            "covariance",
            "burst",
        ):
            assert values[f"{role}.fault.{kind}"] == str(f[role][kind])
    assert status.level == WARN
    assert "imu.fault.stamp_future 3" in status.message and "imu.fault.nan 3" in status.message
    # nothing that was dropped changed the filter: the same estimates as the clean run
    assert len(odometry) == len(reference) > 500
    np.testing.assert_array_equal(positions(odometry), positions(reference))
    assert np.all(np.isfinite(positions(odometry)))
    assert core.counters["imu"].refused == 0 and core.resets == 1  # the finish()


def test_frame_rules():
    core = EkfCore(NavConfig(), TYPES)
    frames = [("imu_link", True), ("pig1/imu_link", True), ("/imu_link", True),
              ("odom", False), ("", False), ("imu_link2", False)]  # fmt: skip
    for k, (frame, ok) in enumerate(frames):
        msg = rosmsg.imu_to_msg(TYPES, 0.01 * k, [0, 0, 0], [0, 0, 9.8], frame_id=frame)
        assert core.on_imu(msg) is ok, frame
    assert core.counters["imu"].faults["frame_id"] == 3
    odo = rosmsg.wheel_to_msg(TYPES, 1.0, 0.0, 0.0)
    odo.child_frame_id = "imu_link"
    assert not core.on_odometer(odo)
    assert core.counters["odometer"].faults["frame_id"] == 1


def test_a_clock_that_goes_back_restarts_the_estimator(run, config):
    """The same 20 s played twice: the second pass is far behind the data's clock; after
    JUMP_CONFIRM agreeing samples the estimator restarts and gives the same estimates again."""
    messages = input_messages(run, t_end=20.0)
    core = EkfCore(config, TYPES)
    handlers = {"imu": core.on_imu, "odometer": core.on_odometer, "mag": core.on_mag,
                "markers": core.on_marker}  # fmt: skip
    first = []
    for _, role, msg in messages:
        handlers[role](msg)
        first += core.poll().odometry
    assert len(first) > 50
    second = []
    for _, role, msg in messages:
        handlers[role](msg)
        second += core.poll().odometry
    assert core.resets == 1
    assert (
        core.counters["imu"].faults["stamp_past"]
        + core.counters["odometer"].faults["stamp_past"]
        + core.counters["mag"].faults["stamp_past"]
        == JUMP_CONFIRM
    )
    np.testing.assert_array_equal(positions(second), positions(first[: len(second)]))
    assert len(second) >= len(first) - 10


def test_a_clock_jump_ahead_is_followed_once_confirmed(config):
    core = EkfCore(config, TYPES)
    imu = lambda t: rosmsg.imu_to_msg(TYPES, t, [0, 0, 0], [0, 0, 9.8])  # noqa: E731
    for k in range(100):
        assert core.on_imu(imu(k * 0.01))
    results = [core.on_imu(imu(500.0 + k * 0.01)) for k in range(JUMP_CONFIRM + 5)]
    assert results == [False] * (JUMP_CONFIRM - 1) + [True] * 6
    assert core.counters["imu"].faults["stamp_future"] == JUMP_CONFIRM
    d = core.nav.diagnostics()  # the engine cannot cross the jump: lost from it on (live_guard)
    assert d["received_imu"] + d["ignored_lost"] == 100 + JUMP_CONFIRM + 5
    assert d["state"] == "lost" and d["lost_since"] == pytest.approx(0.99)
    assert core.clock_s == pytest.approx(500.0 + (JUMP_CONFIRM + 4) * 0.01)


def test_markers_ahead_of_the_data_are_held_not_poisoning(run, config):
    """The run's markers sent first (a survey published in advance), then the data: the markers
    wait for the data to reach them and the estimates are those of the run in stamp order."""
    messages = input_messages(run, t_end=CROP_S)
    reference, _ = clean_estimates(run, config, messages)
    markers = [m for m in messages if m[1] == "markers"]
    reordered = markers + [m for m in messages if m[1] != "markers"]
    core = EkfCore(config, TYPES)
    odometry, datums = feed(core, reordered)
    assert len(datums) == 1
    assert len(odometry) == len(reference)
    np.testing.assert_allclose(positions(odometry), positions(reference), atol=1e-9)
    # once the data run, a marker far ahead of them is a fault (held, never used here)
    late = rosmsg.marker_to_msg(TYPES, rosmsg.marker_from_msg(markers[0][2]))
    core2 = EkfCore(config, TYPES)
    core2.on_imu(rosmsg.imu_to_msg(TYPES, 1.0, [0, 0, 0], [0, 0, 9.8]))
    late.header.stamp = rosmsg.sec_to_stamp(TYPES, 500.0)
    core2.on_marker(late)
    assert core2.counters["markers"].faults["stamp_future"] == 1
    assert core2.nav.diagnostics().get("received_marker", 0) == 0
    # sent along with the data (within BACKLOG_SENT_S of the newest sample): still a fault;
    # sent well after it, the data are behind in their delivery: held, no fault
    for gap, faults in ((0.1, 1), (2.0, 0)):
        core3 = EkfCore(config, TYPES)
        core3.on_imu(rosmsg.imu_to_msg(TYPES, 1.0, [0, 0, 0], [0, 0, 9.8]), sent=100.0)
        core3.on_marker(late, sent=100.0 + gap)
        assert core3.counters["markers"].faults["stamp_future"] == faults


def test_a_topic_arriving_behind_the_others_loses_nothing(run, config):
    """A backlog: from 20 s on the IMU messages reach the node up to 2 s (of stamp time, four
    reorder windows) after the odometer's and magnetometer's of the same stamps, each topic in
    its own order (as a node that fell behind takes them from its queues). Every sample is used
    and the estimates are those of the run in stamp order."""
    messages = input_messages(run, t_end=CROP_S)
    reference, _ = clean_estimates(run, config, messages)
    lag = lambda t, role: min(max(t - 20.0, 0.0), 2.0) if role == "imu" else 0.0  # noqa: E731
    behind = sorted(messages, key=lambda m: m[0] + lag(m[0], m[1]))
    assert behind != messages
    core = EkfCore(config, TYPES)
    odometry, datums = feed(core, behind)
    assert len(datums) == 1
    assert all(sum(c.faults.values()) == 0 for c in core.counters.values())
    assert not any(k.startswith("late_") for k in core.nav.diagnostics())
    assert len(odometry) == len(reference)
    np.testing.assert_allclose(positions(odometry), positions(reference), atol=1e-9)


def test_a_stalled_node_taking_its_queues_in_turn_loses_nothing(run, config):
    """From 20 s on, the queues taken a message per topic per round (a node that was stalled
    catching up), each message with its sender's timestamp (a player at 1x): the 200 Hz IMU
    falls tens of seconds of stamp time behind the odometer, and the marker at 62 s comes in
    the first round, far ahead of the data. It is the data's backlog, not a clock that went back
    nor a marker ahead of its time: no restart, no fault, a single datum, every sample used,
    and the estimates are those of the run in stamp order, across the heading re-run at the
    second marker too (the backlog released the epochs up to 69 s at once, past the
    anchoring at 62 s: those after it come from the re-run, as in stamp order)."""
    messages = input_messages(run, t_end=CROP_S)
    reference, _ = clean_estimates(run, config, messages)
    core = EkfCore(config, TYPES)
    odometry, datums = feed(core, in_turns(messages, 20.0), sent=True)
    assert len(datums) == 1 and core.resets == 1  # the finish()
    assert all(sum(c.faults.values()) == 0 for c in core.counters.values())
    assert len(odometry) == len(reference)
    np.testing.assert_allclose(positions(odometry), positions(reference), atol=1e-9)
    # without the sender's timestamps the marker far ahead of the data is a fault (held, used)
    core = EkfCore(config, TYPES)
    odometry = []
    for _, role, msg in in_turns(messages, 20.0):
        core.on_message(INPUT_TOPICS[role], msg)
        odometry += core.poll().odometry
    odometry += core.finish().odometry
    assert core.counters["markers"].faults["stamp_future"] == 1
    np.testing.assert_allclose(positions(odometry), positions(reference), atol=1e-9)


def test_a_backlog_beyond_the_wait_is_dropped_not_a_restart(run, config):
    """The IMU arriving ever further behind the others, past what the engine waits for
    (MAX_BACKLOG_S): its late samples are dropped and named, and the estimator never restarts
    (each sample still comes after its own topic's previous one)."""
    messages = input_messages(run, t_end=110.0)
    lag = lambda t, role: min(20.0 * max(t - 12.0, 0.0), 70.0) if role == "imu" else 0.0  # noqa: E731
    behind = sorted(messages, key=lambda m: m[0] + lag(m[0], m[1]))
    core = EkfCore(config, TYPES)
    datums, named = 0, 0
    for _, role, msg in behind:
        core.on_message(INPUT_TOPICS[role], msg)
        datums += core.poll().datum is not None
        named += "behind the other inputs (a backlog" in core.counters["imu"].last_problem
    assert core.resets == 0 and datums == 1
    assert core.counters["imu"].faults["stamp_past"] > 100 and named > 100
    assert not any(core.counters[r].faults["stamp_past"] for r in ("odometer", "mag"))


def test_bursts_are_counted_from_the_sent_times():
    core = EkfCore(NavConfig(), TYPES)
    n = 3000
    for k in range(n):  # 3 s of a 1 kHz IMU sent at 1 kHz: no burst
        core.on_imu(rosmsg.imu_to_msg(TYPES, k * 1e-3, [0, 0, 0], [0, 0, 9.8]), sent=k * 1e-3)
    assert core.counters["imu"].faults["burst"] == 0
    for k in range(n, 2 * n):  # 3 s more, sent all at once
        core.on_imu(rosmsg.imu_to_msg(TYPES, k * 1e-3, [0, 0, 0], [0, 0, 9.8]), sent=3.0)
    capacity = BURST_FACTOR * 1000.0 * BURST_ALLOWANCE_S
    assert core.counters["imu"].faults["burst"] == pytest.approx(n - capacity, abs=2)
    assert core.counters["imu"].received == 2 * n  # counted and used
    assert core.nav.diagnostics()["received_imu"] == 2 * n


def test_covariance_problems():
    assert covariance_problem(np.zeros(9), 9) == ""
    assert "4 elements" in covariance_problem(np.zeros(4), 9)
    assert covariance_problem(np.r_[-1.0, np.zeros(8)], 9, flag_ok=True) == ""
    assert "negative" in covariance_problem(np.r_[-1.0, np.zeros(8)], 9)
    assert "finite" in covariance_problem(np.full(36, math.nan), 36)


def test_latency_statistics():
    stats = LatencyStats()
    assert math.isnan(stats.report()["latency_ms.median"])
    stats.add(0.001, 0.003)
    stats.add(0.002, None, n=2)
    stats.add(0.010, 0.020)
    r = stats.report()
    assert r["latency_ms.median"] == pytest.approx(2.0) and r["latency_ms.max"] == pytest.approx(
        10.0
    )
    assert r["latency_ms.estimates"] == 4
    assert r["latency_from_source_ms.median"] == pytest.approx(11.5)
    assert stats.report()["latency_ms.estimates"] == 0  # afresh after each report


def test_imu_grade_auto_is_chosen_at_the_rest_and_reported(run, config):
    import dataclasses

    from pipe_nav_ros.ekf_core import INPUT_TOPICS, declared_imu_noise

    core = EkfCore(dataclasses.replace(config, imu_grade="auto"), TYPES)
    for _, role, msg in input_messages(run, 20.0):  # no finish(): it would restart the engine
        assert core.on_message(INPUT_TOPICS[role], msg)
        core.poll()
    values = {kv.key: kv.value for kv in core.diagnostics(20.0, now=30.0).status[0].values}
    assert values["engine.imu_model"] == "industrial"  # the demo run's IMU
    assert "initial rest" in values["engine.imu_model_reason"]
    # declared variances of the Imu messages are handed to the engine, unknown (0) ones are not
    assert core.nav.declared_imu_noise is None
    msg = rosmsg.imu_to_msg(TYPES, 1.0, [0, 0, 0], [0, 0, 9.8], gyro_var=1e-6, accel_var=4e-4)
    assert declared_imu_noise(msg) == {"gyro_variance": [1e-6] * 3, "accel_variance": [4e-4] * 3}
    fresh = EkfCore(NavConfig(), TYPES)
    fresh.on_imu(msg)
    assert fresh.nav.declared_imu_noise == declared_imu_noise(msg)


def test_a_non_finite_estimate_never_reaches_a_message(run, config):
    import dataclasses

    core = EkfCore(config, TYPES)
    for _, role, msg in input_messages(run, 20.0):
        core.on_message(INPUT_TOPICS[role], msg)
    good = core.nav.poll() + core.nav.finish()
    assert good and core.nav.datum is not None
    bad = dataclasses.replace(good[-1], h=math.nan)
    out = core._output([good[-1], bad])
    assert len(out.odometry) == 1 and core.estimates_nonfinite == 1
    level, message, values = core.health(now=1.0)
    assert level == ERROR and "non-finite" in message and values["estimates_nonfinite"] == 1
