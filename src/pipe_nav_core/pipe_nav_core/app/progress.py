"""How a long job says how far it is: one protocol for every caller (the command line's bar,
the smoother node's /diagnostics, tests).

:func:`pipe_nav_core.app.pipeline.smooth_bag` takes a :class:`Progress` and hands it down, as an
argument, to the smoothing passes (:func:`pipe_nav_core.smooth.passes.smooth_log`) and every filter
pass over the log (:func:`pipe_nav_core.smooth.forward.run_forward`): each stage is named as it
begins and, during each filter pass, the fraction of the pass done is told. :data:`QUIET` is
the default where no one listens.
"""

from __future__ import annotations

from typing import Protocol


class Progress(Protocol):
    """What a job tells its caller while it runs (from the thread that runs it)."""

    def stage(self, text: str) -> None:
        """A new stage begins: one line for people (``RTS smoother (pass 2)``)."""

    def fraction(self, done: float) -> None:
        """The share of the current filter pass done, 0 to 1 (a new stage starts at 0)."""


class Quiet:
    """The Progress of a caller that does not listen."""

    def stage(self, text: str) -> None:
        pass

    def fraction(self, done: float) -> None:
        pass


QUIET = Quiet()
