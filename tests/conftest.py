"""Shared pytest setup.

Makes src/pipe_nav_ros importable for its ROS-free conversion tests. With
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
