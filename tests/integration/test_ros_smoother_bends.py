"""The bend apexes of smoother_node: geometry_msgs/PoseArray on pipe_nav/bends (map, latched,
x along the pipe), built by SmootherJob (ROS-free part) and published by the node (real ROS 2
Jazzy; skipped where rclpy is missing)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pipe_nav_ros.params import smoother_node_settings  # noqa: E402
from pipe_nav_ros.smoother_core import DONE, SmootherJob  # noqa: E402

from pipe_nav_core import NavConfig, dcm_from_quat, rosmsg  # noqa: E402

SAMPLE = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"


def _check_apexes(msg, bends, datum, path_enu) -> None:
    """msg: a PoseArray of ``bends`` in map about ``datum``; path_enu: (N, 3) of the path."""
    assert msg.header.frame_id == "map"
    pos, quat = rosmsg.pose_array_from_msg(msg)
    assert len(pos) == len(bends)
    assert np.isfinite(pos).all() and np.isfinite(quat).all()
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-9)
    want = rosmsg.enu_of(
        datum, [b.lat for b in bends], [b.lon for b in bends], [b.alt for b in bends]
    ).reshape(-1, 3)
    np.testing.assert_allclose(pos, want, atol=1e-6)
    np.testing.assert_allclose(quat, np.array([b.apex_quat_nb for b in bends]), atol=1e-12)
    for p, q in zip(pos, quat, strict=True):
        i = int(np.argmin(np.linalg.norm(path_enu - p, axis=1)))
        assert np.linalg.norm(path_enu[i] - p) < 0.5  # the apex lies on the centreline
        a, b = max(i - 1, 0), min(i + 1, len(path_enu) - 1)
        along = path_enu[b] - path_enu[a]
        x_axis = dcm_from_quat(q)[:, 0]  # the pose's x axis in map
        assert x_axis @ along / np.linalg.norm(along) > 0.9  # along the pipe, downstream


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    out = tmp_path_factory.mktemp("bends") / "out.mcap"
    settings = smoother_node_settings({"bag": str(SAMPLE), "output": str(out)})
    j = SmootherJob(settings, NavConfig(), rosmsg.rosbags_types())
    j.run()
    assert j.state == DONE, j.error
    return j


def test_smoother_job_builds_the_bend_apexes(job):
    products = getattr(job.result, "products", None)
    if products is None:
        pytest.skip("smooth_bag does not return the integrity products yet")
    bends = job.bends()
    assert bends == list(products.bends) and len(bends) > 0  # the sample bends
    msg = job.bends_message()
    ts = rosmsg.jazzy_typestore()
    msg = ts.deserialize_cdr(ts.serialize_cdr(msg, POSE_ARRAY), POSE_ARRAY)
    path_msg, _ = job.messages()
    assert msg.header.stamp == path_msg.header.stamp  # stamped like the path
    _, path_enu, _ = rosmsg.path_from_msg(path_msg)
    _check_apexes(msg, bends, job.result.datum, path_enu)


def test_smoother_job_without_products_publishes_an_empty_array(job):
    class Bare:  # a result without integrity products (an older core)
        datum = job.result.datum

    bare = SmootherJob(job.settings, job.config, job.types)
    bare.state, bare.result, bare.rows = DONE, Bare(), job.rows
    msg = bare.bends_message()
    assert msg.poses == [] and msg.header.frame_id == "map"


def test_output_bag_holds_the_same_bends(job):
    from rosbags.rosbag2.storage_mcap import McapReader

    products = getattr(job.result, "products", None)
    if products is None:
        pytest.skip("smooth_bag does not return the integrity products yet")
    ts = rosmsg.jazzy_typestore()
    rd = McapReader(Path(job.settings["output"]))
    rd.open()
    try:
        (conn,) = [c for c in rd.connections if c.topic == "/pipe_nav/bends"]
        (msg,) = [ts.deserialize_cdr(raw, POSE_ARRAY) for _, _, raw in rd.messages([conn])]
    finally:
        rd.close()
    assert msg.header.stamp == job.messages()[0].header.stamp
    assert len(msg.poses) == len(products.bends)
    pos, quat = rosmsg.pose_array_from_msg(job.bends_message())
    np.testing.assert_allclose(rosmsg.pose_array_from_msg(msg)[0], pos, atol=1e-9)
    np.testing.assert_allclose(rosmsg.pose_array_from_msg(msg)[1], quat, atol=1e-12)


# ------------------------------------------------------------------------------ the node


def test_smoother_node_publishes_latched_bends(request, tmp_path):
    rclpy = pytest.importorskip("rclpy", reason="rclpy (ROS 2 Jazzy) is not installed here")
    from geometry_msgs.msg import PoseArray
    from nav_msgs.msg import Path as PathMsg
    from pipe_nav_ros.smoother_node import SmootherNode
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from ros_graph import spin_until

    assert rclpy is not None
    ctx = request.getfixturevalue("ctx")
    executor, helper, nodes = request.getfixturevalue("graph")
    latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)  # fmt: skip
    node = SmootherNode(
        context=ctx,
        parameter_overrides=[
            Parameter("bag", value=str(SAMPLE)),
            Parameter("output", value=str(tmp_path / "out.mcap")),
        ],
    )
    executor.add_node(node)
    nodes.append(node)
    assert spin_until(executor, lambda: node.job.state != "running", 120.0), "smoothing too slow"
    assert node.job.state == DONE, node.job.error
    assert spin_until(executor, lambda: node._published_at is not None, 5.0)
    if getattr(node.job.result, "products", None) is None:
        pytest.skip("smooth_bag does not return the integrity products yet")
    bends, paths = [], []
    # subscribers that join after the publication still get it (latched)
    helper.create_subscription(PoseArray, "/pipe_nav/bends", bends.append, latched)
    helper.create_subscription(PathMsg, "/pipe_nav/path", paths.append, latched)
    assert spin_until(executor, lambda: bends and paths, 10.0), "no latched /pipe_nav/bends"
    (info,) = helper.get_publishers_info_by_topic("/pipe_nav/bends")
    assert info.topic_type == "geometry_msgs/msg/PoseArray"
    assert info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    run_bends = node.job.result.products.bends
    assert len(run_bends) > 0 and len(bends[0].poses) == len(run_bends)
    assert bends[0].header.stamp == paths[0].header.stamp
    _, path_enu, _ = rosmsg.path_from_msg(paths[0])
    _check_apexes(bends[0], run_bends, node.job.result.datum, path_enu)
