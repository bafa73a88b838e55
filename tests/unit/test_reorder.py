"""The live reorder buffer: samples leave in stamp order; a topic that falls behind the others
(a backlog) is waited for, a silent one is not."""

from __future__ import annotations

import numpy as np
from arrivals import in_turns
from hypothesis import given, settings
from hypothesis import strategies as st
from pipe_nav_core.filter.stream import (
    HOLD_S,
    MAX_BACKLOG_S,
    SILENT_S,
    Released,
    ReorderBuffer,
)

WINDOW = 0.5  # s


def backlog(t: np.ndarray, lag: float) -> np.ndarray:
    """s: a backlog that builds up from 1 s on, at half a second per second, to ``lag``."""
    return np.clip(0.5 * (t - 1.0), 0.0, lag)


def arrivals(stamps: dict[str, np.ndarray], lag: dict[str, float]) -> list[tuple[float, str]]:
    """(stamp, kind) in arrival order: each kind in its own stamp order, arriving behind its
    stamp by a backlog (:func:`backlog`) that reaches ``lag`` s of stamp time."""
    events = [(a, t, k) for k, ts in stamps.items() for t, a in zip(ts, ts + backlog(ts, lag[k]))]
    events.sort()
    return [(t, k) for _, t, k in events]


def assert_in_stamp_order(out: list[tuple[float, str]], items: list[tuple[float, str]]) -> None:
    """Every item left once, in stamp order."""
    assert sorted(out) == sorted(items)
    stamps = [t for t, _ in out]
    assert stamps == sorted(stamps)


def taken(released: Released) -> list[tuple[float, str]]:
    """One release's samples (stamp, kind) in stamp order; each kind's came in its order."""
    for ts, payloads in released.values():
        assert ts == sorted(ts) and len(payloads) == len(ts)
    return sorted((t, k) for k, (ts, _) in released.items() for t in ts)


def play(buf: ReorderBuffer, items: list[tuple[float, str]]) -> list[tuple[float, str]]:
    """Every sample released, release after release (assert_in_stamp_order then asserts that
    no release holds a sample stamped after one of the next)."""
    out = []
    for t, k in items:
        buf.push(t, k, None)
        out += taken(buf.release())
    return out + taken(buf.release(flush=True))


def test_a_topic_behind_the_others_is_waited_for():
    """The IMU arrives 2 s (four windows) behind the odometer and magnetometer: nothing is
    late and everything leaves in stamp order; the window alone lost the IMU."""
    stamps = {"imu": np.arange(0, 20, 0.01), "odometer": np.arange(0, 20, 0.02),
              "mag": np.arange(0, 20, 0.05)}  # fmt: skip
    items = arrivals(stamps, {"imu": 2.0, "odometer": 0.0, "mag": 0.0})
    buf = ReorderBuffer(WINDOW)
    out = play(buf, items)
    assert not buf.late
    assert_in_stamp_order(out, items)
    no_wait = ReorderBuffer(WINDOW, hold=WINDOW, backlog=WINDOW)  # the window alone
    play(no_wait, items)
    assert no_wait.late["imu"] > 1000


def test_a_topic_out_of_its_own_order_leaves_sorted():
    """IMU and odometer samples each arriving up to 0.4 s out of their own order (within the
    window): nothing is late, every sample leaves once and in stamp order, and samples of
    equal stamp keep the order they came in."""
    rng = np.random.default_rng(5)
    stamps = {"imu": np.arange(0, 10, 0.01), "odometer": np.arange(0, 10, 0.02)}
    events = sorted((t + 0.4 * rng.random(), t, k) for k, ts in stamps.items() for t in ts)
    items = [(t, k) for _, t, k in events]
    buf = ReorderBuffer(WINDOW)
    out = play(buf, items)
    assert not buf.late
    assert_in_stamp_order(out, items)
    buf = ReorderBuffer(WINDOW)
    for t, tag in [(1.0, "a"), (0.9, "b"), (1.0, "c"), (0.9, "d")]:
        buf.push(t, "imu", tag)
    assert buf.release(flush=True)["imu"] == ([0.9, 0.9, 1.0, 1.0], ["b", "d", "a", "c"])


class LiveClock:
    """Wall time (s) that runs with the stamps, as it does live: set to each pushed stamp."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_silent_topic_holds_nothing_back():
    """The magnetometer stops at 5 s: from HOLD_S later on samples leave as if it were not
    there (at most HOLD_S of latency, SILENT_S no longer than it); one arriving after that
    is late."""
    assert SILENT_S <= HOLD_S
    clock = LiveClock()
    buf = ReorderBuffer(WINDOW, clock=clock)
    mag = np.arange(0, 5, 0.05)
    for t in mag:
        clock.now = t
        buf.push(t, "mag", None)
    released = []
    for t in np.arange(0, 20, 0.01):
        clock.now = max(clock.now, t)
        buf.push(t, "imu", None)
        released += taken(buf.release())
        if t > mag[-1] + HOLD_S:
            assert buf.horizon == t - WINDOW
        elif t > mag[-1] + WINDOW:
            assert buf.horizon == mag[-1]
    assert released[-1][0] >= 19.0
    assert not buf.push(10.0, "mag", None) and buf.late["mag"] == 1


def test_a_stalled_node_taking_its_queues_in_turn_loses_nothing():
    """A 30 s stall, then the queues taken a message per topic per round: the 200 Hz IMU falls
    behind the 50 Hz odometer by over HOLD_S (up to 3/4 of the backlog), and is waited for
    because it keeps arriving (wall time hardly moves here); nothing is late and everything
    leaves in stamp order."""
    stamps = {"imu": np.arange(0, 40, 0.005), "odometer": np.arange(0.001, 40, 0.02),
              "mag": np.arange(0.002, 40, 0.02)}  # fmt: skip
    items = in_turns(sorted((t, k) for k, ts in stamps.items() for t in ts), 10.0)
    newest, worst = -np.inf, 0.0
    for t, k in items:
        newest = max(newest, t)
        worst = max(worst, newest - t if k == "imu" else 0.0)
    assert HOLD_S < worst < MAX_BACKLOG_S
    buf = ReorderBuffer(WINDOW)
    out = play(buf, items)
    assert not buf.late
    assert_in_stamp_order(out, items)
    hold_only = ReorderBuffer(WINDOW, backlog=HOLD_S)  # the stamp hold alone
    play(hold_only, items)
    assert hold_only.late["imu"] > 1000 and not hold_only.late["odometer"]


def test_a_topic_far_behind_is_waited_for_while_it_arrives():
    """The IMU 20 s of stamp time behind the odometer (past HOLD_S): waited for while its
    samples keep coming, and no longer once it has been silent for SILENT_S of wall time while
    the others came; a pause of every input is no silence."""
    clock = LiveClock()
    buf = ReorderBuffer(WINDOW, clock=clock)
    buf.push(0.0, "imu", None)
    for t in np.arange(0.0, 20.0, 0.02):
        buf.push(t, "odometer", None)
        buf.release()
    assert buf.horizon == 0.0  # the IMU arrived at wall time 0: still arriving
    for t in np.arange(20.0, 20.0 + SILENT_S + 0.1, 0.02):  # the odometer comes, the IMU not
        clock.now += 0.02
        buf.push(t, "odometer", None)
        buf.release()
    assert buf.horizon == t - WINDOW
    paused = ReorderBuffer(WINDOW, clock=clock)  # every input paused (the process stood still)
    paused.push(0.0, "imu", None)
    paused.push(20.0, "odometer", None)
    clock.now += 2 * SILENT_S
    paused.push(20.02, "odometer", None)
    paused.release()
    assert paused.horizon == 0.0  # not a silence of the IMU: still waited for
    far = ReorderBuffer(WINDOW, clock=clock)  # past MAX_BACKLOG_S, arriving or not
    far.push(0.0, "imu", None)
    far.push(MAX_BACKLOG_S + 1.0, "odometer", None)
    far.release()
    assert far.horizon == MAX_BACKLOG_S + 1.0 - WINDOW


def test_markers_do_not_hold_the_release():
    """Markers come seconds apart: they are ordered but never waited for."""
    buf = ReorderBuffer(WINDOW)
    buf.push(1.0, "marker", None)
    for t in np.arange(0, 3, 0.01):
        buf.push(t, "imu", None)
    buf.release()
    assert buf.horizon == np.arange(0, 3, 0.01)[-1] - WINDOW


@settings(max_examples=60, deadline=None)
@given(
    lags=st.tuples(*[st.floats(0.0, HOLD_S - 0.5)] * 3),
    jitter=st.floats(0.0, WINDOW * 0.9),
    seed=st.integers(0, 2**16),
)
def test_any_lags_within_the_hold_lose_nothing(lags, jitter, seed):
    """Three topics at different rates, each in its own order but behind its stamps by its own
    backlog (within HOLD_S) and jitter: every sample leaves, once, in stamp order."""
    rng = np.random.default_rng(seed)
    stamps = {"imu": np.arange(0, 12, 0.01), "odometer": np.arange(0.003, 12, 0.02),
              "mag": np.arange(0.007, 12, 0.05)}  # fmt: skip
    lag = dict(zip(stamps, lags, strict=True))
    events = []
    for k, ts in stamps.items():  # each topic in its own order
        arrive = np.maximum.accumulate(ts + backlog(ts, lag[k]) + jitter * rng.random(len(ts)))
        events += [(a, t, k) for t, a in zip(ts, arrive)]
    events.sort()
    items = [(t, k) for _, t, k in events]
    buf = ReorderBuffer(WINDOW)
    out = play(buf, items)
    assert not buf.late
    assert_in_stamp_order(out, items)
