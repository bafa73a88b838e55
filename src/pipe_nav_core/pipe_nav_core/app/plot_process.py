"""The report PNG drawn in a child process, on the machine's second core.

Importing matplotlib and rendering the report cost as much as smoothing a short run. A
:class:`PlotProcess` is forked when a command starts; on the parent's word
(:meth:`PlotProcess.warm`) it imports matplotlib and loads its fonts while the parent smooths
the bag: at once for a small bag (the parent's start-up leaves a core idle), for a large one
once it is read (reading it and the first filter pass beside it keep both cores busy, the
passes after it leave one core partly idle). The parent then hands it the finished centreline
and writes its other products while the child draws. Where ``fork`` is not available (or the
child died) the plot is drawn in the calling process, as :func:`plots.plot_report` always was.

The child ignores Ctrl-C (the parent, in the same process group, handles it and cleans up), and
exits when the parent closes the pipe or dies.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from multiprocessing.connection import Connection
from types import TracebackType
from typing import Any

_WARM = "warm"  # the parent's word to load matplotlib now (PlotProcess.warm)


def _warm() -> None:
    """Import matplotlib's Agg canvas and draw once what every report draws (text, a legend,
    a band), so fonts are loaded before the data."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2, 2), dpi=20)
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.plot([1.0, 2.0], [1e-3, 1e-1], label="strain [%]")
    ax.fill_between([1.0, 2.0], [1e-3, 1e-2], [1e-2, 1e-1], alpha=0.25)
    ax.set_title("0 m")
    ax.legend(fontsize=8)
    fig.savefig(io.BytesIO(), format="png")
    from pipe_nav_core.app.plots import prepare_figure

    prepare_figure()  # the report's empty figure, before the data arrives


def _serve(conn: Connection, parent_end: Connection, warm: bool) -> None:
    parent_end.close()  # else the parent closing its end would not reach this one as EOF
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        if warm:
            _warm()
        while True:
            try:
                request = conn.recv()
            except (EOFError, OSError):
                return
            if request == _WARM:
                if not warm:
                    _warm()
                    warm = True
                continue
            args, kwargs = request
            try:
                from pipe_nav_core.app.plots import plot_report

                plot_report(*args, **kwargs)
                conn.send(None)
            except Exception as exc:  # reported to the parent, which raises it
                conn.send((isinstance(exc, OSError), f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


class PlotProcess:
    """A child process that draws report PNGs (:func:`plots.plot_report`) on request.

    ``with PlotProcess.start(warm=False) as plotter:``, ``plotter.warm()`` when a core is to
    spare (``start()``: at once), then ``plotter.submit(path, traj, ...)`` (the arguments of
    plot_report) and, before the PNG is needed, ``plotter.wait()``, which raises OSError (a
    file system error) or RuntimeError (any other) if drawing failed. Without a child (no fork
    on this platform) submit draws in place.
    """

    def __init__(self, process: Any | None, conn: Connection | None, told: bool = False) -> None:
        self._process = process
        self._conn = conn
        self._pending = False
        self._told = told  # to warm (warm() tells it once)

    @classmethod
    def start(cls, warm: bool = True) -> PlotProcess:
        """Fork the child now, so that it warms up while the caller works: at once, or with
        ``warm=False`` when told (:meth:`warm`)."""
        if "fork" not in mp.get_all_start_methods() or os.environ.get("PIPE_NAV_PLOT_INLINE"):
            return cls(None, None)
        ctx = mp.get_context("fork")
        parent, child = ctx.Pipe()
        process = ctx.Process(
            target=_serve, args=(child, parent, warm), daemon=True, name="pipe-nav-plot"
        )
        process.start()
        child.close()
        return cls(process, parent, told=warm)

    def warm(self) -> None:
        """Have the child import matplotlib and draw the report's empty figure now, while the
        caller leaves a core to spare (unless it was told already); a plot submitted without it
        loads them first."""
        if self._conn is not None and not self._told:
            self._told = True
            try:
                self._conn.send(_WARM)
            except (OSError, ValueError):
                self.close()  # the child is gone: submit draws in place

    def submit(self, *args: Any, **kwargs: Any) -> None:
        """Start drawing plot_report(*args, **kwargs); in place if there is no child."""
        if self._conn is not None and self._process is not None and self._process.is_alive():
            try:
                self._conn.send((args, kwargs))
                self._pending = True
                return
            except (OSError, ValueError):
                self.close()
        from pipe_nav_core.app.plots import plot_report

        plot_report(*args, **kwargs)

    def wait(self) -> None:
        """Until the submitted plot is written; OSError or RuntimeError naming why if not."""
        if not self._pending:
            return
        self._pending = False
        assert self._conn is not None
        try:
            error = self._conn.recv()
        except (EOFError, OSError):
            error = (False, "its process ended")
        if error:
            is_os, why = error
            raise (OSError if is_os else RuntimeError)(f"the report plot failed: {why}")

    def close(self) -> None:
        """End the child at once: nothing it may still be doing is wanted (a plot no one
        waits for, or loading matplotlib for a run that ended early)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._process is not None:
            self._process.terminate()
            self._process.join(timeout=5.0)
            if self._process.is_alive():
                self._process.kill()
            self._process = None
        self._pending = False

    def __enter__(self) -> PlotProcess:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
