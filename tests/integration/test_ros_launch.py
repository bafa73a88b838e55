"""The launch files under real ROS 2 Jazzy: a launch_testing run per
tests/integration/launch/*_launch_test.py.

Jazzy's launch_testing pytest plugin needs pytest 7 (it is disabled in pytest.ini), so each
launch test runs as ``python -m launch_testing.launch_test FILE --junit-xml ...`` in a process
of its own, on a ROS domain of its own, writing under tmp_path; this test asserts its exit
status 0 and that its JUnit report lists active and post-shutdown tests with no failure, error
or skip, and that no process it started is left running. The runner's output is shown on
failure. Skipped where rclpy, launch_testing or the built pipe_nav_ros package is missing.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytest.importorskip("rclpy", reason="rclpy (ROS 2 Jazzy) is not installed here")
pytest.importorskip("launch_testing.launch_test", reason="launch_testing (ROS 2) is missing")

LAUNCH_TESTS = sorted((Path(__file__).parent / "launch").glob("*_launch_test.py"))
# one launch test: 5 to 45 s on a loaded 2-core machine with the core's kernels compiled; the
# first run after an edit of the core compiles them (minutes)
TIMEOUT_S = 400.0
_domains = itertools.count()


def new_domain() -> int:
    """A ROS domain for one launch test: 30..99, away from the ids people use by hand and from
    tests/integration/test_ros_drivers.py's 120..219; all below 102, where Linux DDS ports are
    safe."""
    return 30 + (os.getpid() * 11 + next(_domains)) % 70


def _package_installed() -> bool:
    from ament_index_python.packages import (
        PackageNotFoundError,
        get_package_share_directory,
    )

    try:
        get_package_share_directory("pipe_nav_ros")
    except PackageNotFoundError:
        return False
    return True


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def _stop_group(pgid: int) -> None:
    """SIGINT the process group (launch's clean stop), then SIGKILL what is left after 15 s."""
    for sig, wait_s in ((signal.SIGINT, 15.0), (signal.SIGKILL, 5.0)):
        if not _group_alive(pgid):
            return
        os.killpg(pgid, sig)
        for _ in range(int(wait_s * 10)):
            if not _group_alive(pgid):
                return
            time.sleep(0.1)


def test_launch_tests_found():
    assert [p.name for p in LAUNCH_TESTS] == [
        "live_launch_test.py",
        "replay_launch_test.py",
        "smooth_launch_test.py",
    ]


@pytest.mark.parametrize("launch_test", LAUNCH_TESTS, ids=lambda p: p.name.split("_")[0])
def test_launch_file(launch_test: Path, tmp_path: Path) -> None:
    if not _package_installed():
        pytest.skip("pipe_nav_ros is not built: colcon build, then source install/setup.bash")
    junit = tmp_path / "junit.xml"
    env = dict(
        os.environ,
        ROS_DOMAIN_ID=str(new_domain()),
        ROS_LOG_DIR=str(tmp_path / "ros_log"),
        PIPE_NAV_LAUNCH_TMP=str(tmp_path),
        PYTHONUNBUFFERED="1",
    )
    cmd = [sys.executable, "-m", "launch_testing.launch_test", str(launch_test)]
    cmd += ["--junit-xml", str(junit)]
    proc = subprocess.Popen(
        cmd,
        env=env,
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        errors="replace",
        start_new_session=True,  # its own process group: the nodes it launches are in it too
    )
    try:
        output, _ = proc.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        _stop_group(proc.pid)
        output, _ = proc.communicate()
        pytest.fail(f"{launch_test.name} still running after {TIMEOUT_S:.0f} s:\n{output}")
    finally:
        left = _group_alive(proc.pid)
        _stop_group(proc.pid)
    print(output)  # shown by pytest on failure
    assert proc.returncode == 0, f"{launch_test.name} failed (exit {proc.returncode}):\n{output}"
    assert not left, f"{launch_test.name} left processes running:\n{output}"
    cases = ET.parse(junit).getroot().iter("testcase")
    names = {c.get("name"): [e.tag for e in c] for c in cases}
    problems = {n: tags for n, tags in names.items() if set(tags) & {"failure", "error", "skipped"}}
    assert not problems, f"{launch_test.name}: {problems}\n{output}"
    assert any(n.startswith("test_exit_codes") for n in names), names  # post-shutdown ran
    assert len(names) >= 4, names
