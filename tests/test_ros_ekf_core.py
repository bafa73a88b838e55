"""ekf_node's message handling (EkfCore) with rosbags' Jazzy message classes, no ROS needed:
a simulated run goes in as sensor messages, Odometry / datum / diagnostics come out."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pipe_nav_core.config import NavConfig
from pipe_nav_core.earth import geodetic_to_enu
from pipe_nav_core.io import rosmsg
from pipe_nav_core.sim import simulate
from pipe_nav_ros.ekf_core import ERROR, OK, WARN, EkfCore, twist_covariance

from pipe_nav_core import attitude as att

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


def feed(core, messages):
    handlers = {
        "imu": core.on_imu,
        "odometer": core.on_odometer,
        "mag": core.on_mag,
        "markers": core.on_marker,
    }
    odometry, datums = [], []
    for _, role, msg in messages:
        assert handlers[role](msg)
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
    enu_true = geodetic_to_enu(truth.lat, truth.lon, truth.h, d.lat, d.lon, d.alt)
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
    from pipe_nav_core.engine import NavEstimate

    q = att.quat_from_dcm(att.dcm_from_euler(0.0, 0.0, math.radians(90.0)))  # nose east
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
    """A consumer-MEMS run (drag180) on the default industrial noise model: once the filter
    navigates, /diagnostics turns WARN and names the setting to check."""
    run = simulate("drag180", 1)
    core = EkfCore(NavConfig(), TYPES)
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
    assert c["imu"].malformed == 2 and c["markers"].malformed == 1
    assert len(problems) == 3 and all("malformed" in text for _, text in problems)
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
    assert core.on_message("/pig/imu", msg, topics={"imu": "/pig/imu"})
    assert core.counters["imu"].received == 2
