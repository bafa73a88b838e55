"""Shared pytest setup.

Makes src/pipe_nav_ros importable for its ROS-free conversion tests and, where rclpy is there,
gives the node tests their fixtures (``ctx``: an rclpy context on a ROS domain of the test's own;
``graph``: an executor spun from the test thread, a helper node, and the nodes to clean up). With
``PIPE_NAV_REQUIRE_ROS=1`` (CI on a machine with ROS 2 Jazzy, see .ci/run) a skipped test fails
the run: the node, launch and bag tests must run for real there, not skip for want of rclpy.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROS_PKG = ROOT / "src" / "pipe_nav_ros"
if ROS_PKG.is_dir() and str(ROS_PKG) not in sys.path:
    sys.path.insert(0, str(ROS_PKG))

try:
    import rclpy
except ImportError:  # the node tests skip
    rclpy = None

if rclpy is not None:
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from ros_graph import own_domain

    @pytest.fixture
    def ctx():  # type: ignore[no-untyped-def]
        context = Context()
        rclpy.init(context=context, domain_id=own_domain())
        yield context
        rclpy.try_shutdown(context=context)

    @pytest.fixture
    def graph(ctx):  # type: ignore[no-untyped-def]
        executor = SingleThreadedExecutor(context=ctx)
        helper = rclpy.create_node("pipe_nav_test_helper", context=ctx)
        executor.add_node(helper)
        nodes = [helper]
        yield executor, helper, nodes
        for node in nodes:
            if hasattr(node, "close"):
                node.close()
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()


REQUIRE_ROS = os.environ.get("PIPE_NAV_REQUIRE_ROS", "") not in ("", "0")
_skipped: list[str] = []


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.skipped:
        _skipped.append(report.nodeid)


def pytest_collectreport(report: pytest.CollectReport) -> None:
    if report.skipped:
        _skipped.append(report.nodeid)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if REQUIRE_ROS and _skipped and exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter) -> None:  # type: ignore[no-untyped-def]
    if REQUIRE_ROS and _skipped:
        terminalreporter.write_line(
            f"PIPE_NAV_REQUIRE_ROS is set and {len(_skipped)} test(s) skipped "
            f"(each must run on this ROS 2 machine): {', '.join(_skipped[:10])}",
            red=True,
        )
