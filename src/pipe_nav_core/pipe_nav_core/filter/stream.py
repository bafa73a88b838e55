"""Time ordering of samples from several topics that may arrive out of order.

Samples are held for ``window`` seconds of stamp time and released in stamp order; a sample
older than what was already released is late: it is counted and dropped.
"""

from __future__ import annotations

import heapq
import itertools
from collections import defaultdict
from typing import Any


class ReorderBuffer:
    """Merges pushed samples of several kinds into one stream ordered by stamp."""

    def __init__(self, window: float) -> None:
        self.window = float(window)
        self._heap: list[tuple[float, int, str, Any]] = []
        self._seq = itertools.count()
        self.newest = float("-inf")
        self.horizon = float("-inf")  # everything stamped at or before it has been released
        self.late: dict[str, int] = defaultdict(int)

    def push(self, t: float, kind: str, payload: Any) -> bool:
        """Add one sample; False (and counted) if it is older than the release horizon."""
        if t <= self.horizon:
            self.late[kind] += 1
            return False
        heapq.heappush(self._heap, (t, next(self._seq), kind, payload))
        if t > self.newest:
            self.newest = t
        return True

    def release(self, flush: bool = False) -> list[tuple[float, str, Any]]:
        """Samples whose stamps are at least ``window`` older than the newest, in stamp order
        (all of them when flush)."""
        cutoff = float("inf") if flush else self.newest - self.window
        out = []
        heap = self._heap
        while heap and heap[0][0] <= cutoff:
            t, _, kind, payload = heapq.heappop(heap)
            out.append((t, kind, payload))
        if cutoff > self.horizon:
            self.horizon = cutoff
        return out

    def __len__(self) -> int:
        return len(self._heap)
