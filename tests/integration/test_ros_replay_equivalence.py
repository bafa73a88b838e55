"""ekf_node and ``pipe-nav replay`` are one estimator: the same bag gives the same estimates.

The ekf_node path here is its message core (EkfCore) fed the bag's messages in log order, as
rosbags deserializes them (the node receives the same messages from ``ros2 bag play``); the
other path is pipe_nav_core.app.replay.replay_bag, what ``pipe-nav replay`` runs.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pipe_nav_core.smooth.logs import slice_log  # noqa: E402  (a fixture's internal)
from pipe_nav_ros.ekf_core import EkfCore  # noqa: E402
from rosbags import highlevel

from pipe_nav_core import (  # noqa: E402
    NavConfig,
    SensorLog,
    replay_bag,
    rosmsg,
    simulate,
    write_sensor_bag,
)

CROP_S = 90.0


def cropped(log: SensorLog, t_end: float) -> SensorLog:
    """The log's samples and markers stamped up to and including ``t_end`` (s)."""
    return slice_log(log, -math.inf, float(np.nextafter(t_end, math.inf)))


@pytest.fixture(scope="module")
def bag_and_config(tmp_path_factory):
    run = simulate("demo", 3)
    path = tmp_path_factory.mktemp("equivalence") / "demo.mcap"
    write_sensor_bag(path, cropped(run.log, CROP_S))
    return path, NavConfig.from_dict(run.scenario.estimator_settings())


def ekf_node_estimates(path, config):
    """EkfCore over the bag's messages in log order; the estimates and the Odometry messages."""
    core = EkfCore(config, rosmsg.rosbags_types())
    estimates, odometry, datums = [], [], []
    with highlevel.AnyReader([path], default_typestore=rosmsg.jazzy_typestore()) as reader:
        for conn, _log_time, raw in reader.messages():
            core.on_message(conn.topic, reader.deserialize(raw, conn.msgtype))
            out = core.poll()
            estimates += out.estimates
            odometry += out.odometry
            datums += [out.datum] if out.datum is not None else []
    out = core.finish()
    return estimates + out.estimates, odometry + out.odometry, datums, core


def test_ekf_node_core_and_pipe_nav_replay_agree(bag_and_config, tmp_path):
    path, config = bag_and_config
    result, _report = replay_bag(path, tmp_path / "replay.mcap", config=config)
    ours, odometry, datums, core = ekf_node_estimates(path, config)

    theirs = result.estimates
    assert len(theirs) > 100
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs, strict=True):
        assert a.t == b.t
        assert (a.lat, a.lon, a.h) == (b.lat, b.lon, b.h)
        np.testing.assert_array_equal(a.quat_nb, b.quat_nb)
        np.testing.assert_array_equal(a.vel_n, b.vel_n)
        np.testing.assert_array_equal(a.cov_pose, b.cov_pose)
        assert a.distance == b.distance and a.status == b.status
    # one datum, the same (published once, in degrees)
    assert len(datums) == 1
    datum = rosmsg.datum_from_msg(datums[0])
    assert (datum.lat, datum.lon, datum.alt) == pytest.approx(
        (result.datum.lat, result.datum.lon, result.datum.alt), rel=1e-15
    )

    # every estimate made it into an Odometry message (the datum is the first marker)
    assert len(odometry) == len(ours)
    o = rosmsg.odometry_from_msg(odometry[-1])
    expected = rosmsg.enu_of(result.datum, ours[-1].lat, ours[-1].lon, ours[-1].h).reshape(3)
    np.testing.assert_allclose(o["position"], expected, atol=1e-9)
    assert sum(c.malformed + c.refused for c in core.counters.values()) == 0
