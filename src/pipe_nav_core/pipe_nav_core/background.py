"""Work on the other core: a function run on a thread of its own while the caller goes on.

The package's heavy work lets go of the GIL (the compiled kernels declared ``nogil``, numpy's
loops), so two such jobs run on two cores: the welds beside the bends, the backward filter of
the two-filter smoother beside the forward one.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any


class Background:
    """``fn(*args)`` in a daemon thread named ``name`` (an interrupted run does not wait for it
    at exit); :meth:`result` waits for it and returns its value or raises its exception."""

    def __init__(self, name: str, fn: Callable[..., object], *args: object) -> None:
        self._out: list[object] = []
        self._error: list[BaseException] = []

        def run() -> None:
            try:
                self._out.append(fn(*args))
            except BaseException as e:  # handed to the caller by result()
                self._error.append(e)

        self._thread = threading.Thread(target=run, name=name, daemon=True)
        self._thread.start()

    def result(self) -> Any:
        self._thread.join()
        if self._error:
            raise self._error[0]
        return self._out[0]
