"""The order in which a stalled node takes its input messages: the reorder tests' backlog."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def in_turns(items: Sequence[tuple[Any, ...]], stall_s: float) -> list[tuple[Any, ...]]:
    """``items`` (stamp s, topic, ...) in stamp order, as a node stalled from ``stall_s`` on
    takes them: in stamp order before it, then one per topic in turn from each topic's queue
    (an executor's round) until every queue is empty."""
    before = [m for m in items if m[0] < stall_s]
    queues: dict[Any, list[tuple[Any, ...]]] = {}
    for m in items:
        if m[0] >= stall_s:
            queues.setdefault(m[1], []).append(m)
    after = []
    while any(queues.values()):
        for q in queues.values():
            if q:
                after.append(q.pop(0))
    return before + after
