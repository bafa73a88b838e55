"""Helpers of the node tests (their fixtures ``ctx`` and ``graph`` are in conftest.py): a ROS
domain of each test's own, spinning until something happens, and a command run in its own
process group with its output in a file."""

from __future__ import annotations

import contextlib
import itertools
import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from rclpy.executors import SingleThreadedExecutor

_domains = itertools.count()


def own_domain() -> int:
    """A ROS domain for one test, 120..219: away from the ids people use by hand, and from
    test to test (the pid spreads runs of the suite that overlap)."""
    return 120 + (os.getpid() * 7 + next(_domains)) % 100


def spin_until(executor: SingleThreadedExecutor, predicate: Callable[[], bool],
               timeout: float = 10.0) -> bool:  # fmt: skip
    """Spin until ``predicate()`` holds or ``timeout`` s pass; the predicate's last value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        executor.spin_once(timeout_sec=0.02)
    return predicate()


def ros2_with_workspace() -> str:
    """The ``ros2`` command, for tests that start the installed nodes; skips the test where
    it is not on PATH or pipe_nav_ros is not installed."""
    ros2 = shutil.which("ros2")
    if ros2 is None:
        pytest.skip("the ros2 command is not on PATH (source .ci/ros-env)")
    try:
        from ament_index_python.packages import get_package_prefix

        get_package_prefix("pipe_nav_ros")
    except (ImportError, LookupError):
        pytest.skip("pipe_nav_ros is not installed (colcon build; source install/setup.bash)")
    return ros2


class LoggedProcess:
    """A command in its own process group, its output (stdout and stderr) in a log file."""

    def __init__(self, args: list[str], env: dict[str, str], log: Path) -> None:
        self.args, self.log = args, log
        self._out = log.open("wb")
        self.proc = subprocess.Popen(
            args, stdout=self._out, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_for(self, pattern: str, timeout: float = 60.0) -> None:
        """Until the output matches the regular expression ``pattern``; AssertionError with
        the output's tail if it does not within ``timeout`` s or the process ends first."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if re.search(pattern, self.output()):
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(
            f"{pattern!r} not seen from {' '.join(self.args[:4])}:\n{self.output()[-3000:]}"
        )

    def wait(self, timeout: float = 60.0) -> int:
        """The exit status; AssertionError with the output's tail after ``timeout`` s."""
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"{' '.join(self.args[:4])} still running after {timeout} s:\n"
                f"{self.output()[-3000:]}"
            ) from None

    def interrupt(self, timeout: float = 20.0, times: int = 1) -> int:
        """Ctrl-C to the group ``times`` times (``ros2 launch`` delivers it twice: to the
        terminal's group and forwarded); the exit status."""
        for k in range(times):
            if self.proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGINT)
            if k + 1 < times:
                time.sleep(0.05)
        return self.wait(timeout)

    def stop(self) -> None:
        """Ctrl-C, then SIGKILL to the group if it is still running; closes the log."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError, AssertionError):
                self.interrupt(timeout=10.0)
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=10.0)
        self._out.close()
