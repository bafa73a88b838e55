"""Helpers of the node tests (their fixtures ``ctx`` and ``graph`` are in conftest.py): a ROS
domain of each test's own, and spinning until something happens."""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Callable

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
