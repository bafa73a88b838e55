"""The per-topic checks of the bag reader (io.topic_checks.TopicState), on hand-made samples."""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pipe_nav_core.filter.stream import ReorderBuffer
from pipe_nav_core.io.bagdecode import Pieces
from pipe_nav_core.io.stamps import NS_PER_S
from pipe_nav_core.io.topic_checks import REORDER_WINDOW_S, TopicState
from pipe_nav_core.io.topics import (
    SKIP_DUPLICATE,
    SKIP_LATE,
    SKIP_NON_MONOTONIC,
    SKIP_TIME_JUMP,
    BagReport,
)


def _odo(seconds: list[float]) -> Pieces:
    ns = np.round(np.asarray(seconds) * NS_PER_S).astype(np.int64)
    return Pieces(ns, {"distance": np.asarray(seconds, float), "speed": np.ones(len(ns))})


def _state() -> TopicState:
    return TopicState("/odom", "odometer", BagReport())


def _skipped(st: TopicState, reason: str) -> int:
    return st.report.skipped_by_topic.get(st.topic, {}).get(reason, 0)


def test_isolated_jump_ahead_is_dropped_and_the_last_sample_waits_for_its_successor():
    st = _state()
    st.ingest(_odo([0.0, 0.1, 5.0, 0.2, 0.3]))
    assert st.pending is not None and len(st.pending) == 1  # 0.3 s: no successor yet
    st.flush_pending()
    out = st.emit(None)
    assert out.ns.tolist() == [int(x * NS_PER_S) for x in (0.0, 0.1, 0.2, 0.3)]
    assert _skipped(st, SKIP_TIME_JUMP) == 1


def test_small_disorder_is_sorted_larger_is_dropped_and_repeats_keep_the_first():
    st = _state()
    back = 2 * REORDER_WINDOW_S
    st.ingest(_odo([1.0, 1.2, 1.1, 1.2, 1.3, 1.3 - back, 1.4]), final=True)
    out = st.emit(None)
    assert out.ns.tolist() == [int(x * NS_PER_S) for x in (1.0, 1.1, 1.2, 1.3, 1.4)]
    assert _skipped(st, SKIP_NON_MONOTONIC) == 1
    assert _skipped(st, SKIP_DUPLICATE) == 1
    assert st.report.counts["/odom"] == 5


def test_streaming_drops_what_arrives_after_its_chunk_went_out():
    st = _state()
    st.ingest(_odo([1.0, 1.5, 2.1]), final=True)
    first = st.emit(2 * NS_PER_S)
    assert first.ns.tolist() == [NS_PER_S, int(1.5 * NS_PER_S)]
    st.ingest(_odo([2.3, 1.95, 2.7]), final=True)  # 1.95 s: inside the window, but too late
    rest = st.emit(None)
    assert rest.ns.tolist() == [int(x * NS_PER_S) for x in (2.1, 2.3, 2.7)]
    assert _skipped(st, SKIP_LATE) == 1


def test_not_the_live_reorder_buffer():
    """Why the reader keeps its own window: stream.ReorderBuffer keeps a sample far behind the
    newest one as long as it was not released, where the reader drops it."""
    seconds = [1.0, 2.0, 2.0 - 3 * REORDER_WINDOW_S, 2.1]
    st = _state()
    st.ingest(_odo(seconds), final=True)
    kept = st.emit(None).ns.tolist()
    buf = ReorderBuffer(REORDER_WINDOW_S)
    for t in seconds:
        buf.push(t, "odometer", None)
    released = buf.release(flush=True)["odometer"][0]
    assert len(kept) == 3
    assert len(released) == 4


_FAULT = st.sampled_from(["ok", "ok", "ok", "swap", "back", "repeat", "jump"])


@settings(max_examples=80, deadline=None)
@given(faults=st.lists(_FAULT, min_size=1, max_size=60), cuts=st.lists(st.integers(1, 60)))
@example(faults=["ok", "ok", "jump", "ok"], cuts=[3])  # a glitch that ends a batch
@example(faults=["ok", "ok", "ok", "back", "ok"], cuts=[3])  # one that begins one
def test_the_checks_keep_the_same_samples_however_the_batches_are_cut(faults, cuts):
    """The reader gathers a few chunks' samples before the checks (bagread.CHECK_MESSAGES):
    the kept samples, their order and the counts do not depend on where batches end."""
    t = [1.0 + 0.01 * i for i in range(len(faults))]
    for i, fault in enumerate(faults):
        if fault == "swap" and i:
            t[i - 1], t[i] = t[i], t[i - 1]
        elif fault == "back":
            t[i] -= 2 * REORDER_WINDOW_S
        elif fault == "repeat" and i:
            t[i] = t[i - 1]
        elif fault == "jump":
            t[i] += 5.0
    whole = _state()
    whole.ingest(_odo(t))
    whole.flush_pending()
    want = whole.emit(None)
    cut = _state()
    edges = sorted({0, len(t), *(c % (len(t) + 1) for c in cuts)})
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        cut.ingest(_odo(t[a:b]))
    cut.flush_pending()
    got = cut.emit(None)
    assert got.ns.tolist() == want.ns.tolist()
    assert got.values["distance"].tolist() == want.values["distance"].tolist()
    assert cut.report.skipped_by_topic == whole.report.skipped_by_topic
