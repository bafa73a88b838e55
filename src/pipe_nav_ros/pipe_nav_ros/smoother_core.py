"""The work of smoother_node, without rclpy: run ``smooth_bag`` and make the output messages.

:class:`SmootherJob` runs :func:`pipe_nav_core.app.pipeline.smooth_bag` (the same function as
``pipe-nav smooth``: it writes the output MCAP and the optional CSV / GeoJSON / KML / plot),
records its progress for the logs and /diagnostics, and builds the nav_msgs/Path, the datum
NavSatFix and the bend apexes' geometry_msgs/PoseArray to publish latched. The node runs it in a
thread and publishes what it returns.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

from pipe_nav_core import NavConfig, rosmsg

OK, WARN, ERROR = 0, 1, 2
DIAGNOSTIC_NAME = "pipe_nav: smoother_node"
RUNNING, DONE, FAILED = "running", "done", "failed"


class SmootherJob:
    """One smoothing run.

    settings: :func:`pipe_nav_ros.params.smoother_node_settings` values; config: the estimator
    settings; types: message classes (rclpy_types() or rosbags').
    """

    def __init__(self, settings: Mapping[str, Any], config: NavConfig, types: Any) -> None:
        self.settings = dict(settings)
        self.config = config
        self.types = types
        self.state = RUNNING
        self.error = ""
        self.result: Any = None
        self.report: Any = None
        self.rows: Any = None
        self.warnings: list[str] = []
        self.fraction: float | None = None
        self.stage = "starting"
        self.started = time.monotonic()
        self.finished: float | None = None
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ running
    def told(self) -> _Told:
        """What smooth_bag tells this job as it runs (pipe_nav_core.app.progress.Progress)."""
        return _Told(self)

    def run(self) -> None:
        """Smooth the bag (blocking); afterwards ``state`` is DONE or FAILED (``error``)."""
        s = self.settings
        try:
            from pipe_nav_core import Outputs, centreline_rows, smooth_bag

            outputs = Outputs(
                bag=s["output"],
                csv=s["csv"] or None,
                geojson=s["geojson"] or None,
                kml=s["kml"] or None,
                plot=s["plot"] or None,
            )
            result, report = smooth_bag(
                s["bag"],
                outputs,
                config=self.config,
                method=s["method"],
                iterations=s["iterations"],
                markers_csv=s["markers_csv"] or None,
                spacing=s["spacing"],
                progress=self.told(),
            )
            # the path published is the one written to the output bag
            rows = centreline_rows(result, s["spacing"])
        except Exception as exc:  # noqa: BLE001 - reported as the job's failure, not a crash
            with self._lock:
                self.error = f"{type(exc).__name__}: {exc}"
                self.state = FAILED
                self.finished = time.monotonic()
            return
        with self._lock:
            self.result, self.report, self.rows = result, report, rows
            self.warnings = list(getattr(report, "warnings", []))
            self.state = DONE
            self.fraction = 1.0
            self.stage = "done"
            self.finished = time.monotonic()

    def start(self) -> threading.Thread:
        """Run in a daemon thread."""
        thread = threading.Thread(target=self.run, name="smooth_bag", daemon=True)
        thread.start()
        return thread

    # ------------------------------------------------------------------ output
    def messages(self) -> tuple[Any, Any]:
        """(nav_msgs/Path in map, datum NavSatFix) of a finished run."""
        if self.state != DONE or self.result is None:
            raise RuntimeError("the smoothing run has not finished successfully")
        traj, datum = self.rows, self.result.datum
        path = rosmsg.path_to_msg(self.types, traj, datum)
        t0 = float(traj.t[0]) if len(traj.t) else 0.0
        return path, rosmsg.datum_to_msg(self.types, datum, t0)

    def bends(self) -> list[Any]:
        """The bends of a finished run (``result.products.bends``; [] without products)."""
        products = getattr(self.result, "products", None)
        return list(getattr(products, "bends", None) or [])

    def bends_message(self) -> Any:
        """geometry_msgs/PoseArray of the bend apexes in map (one Pose per bend, x along the
        pipe), stamped like the path (its last sample); empty without bends."""
        if self.state != DONE or self.result is None:
            raise RuntimeError("the smoothing run has not finished successfully")
        t = float(self.rows.t[-1]) if len(self.rows.t) else 0.0
        return rosmsg.bends_to_msg(self.types, self.bends(), self.result.datum, t)

    def health(self) -> tuple[int, str, dict[str, Any]]:
        """(level, message, values) for /diagnostics and the progress log."""
        with self._lock:
            state, fraction, stage, error = self.state, self.fraction, self.stage, self.error
            end = self.finished
        elapsed = (end if end is not None else time.monotonic()) - self.started
        values: dict[str, Any] = {
            "state": state,
            "stage": stage,
            "progress": "?" if fraction is None else f"{100.0 * fraction:.1f} %",
            "elapsed_s": round(elapsed, 1),
            "bag": self.settings["bag"],
            "output": self.settings["output"],
            "method": self.settings["method"],
        }
        if state == FAILED:
            return ERROR, f"smoothing failed: {error}", values
        if state == DONE:
            summary = getattr(self.result, "summary", None) or {}
            for key, value in dict(summary).items():
                values[f"summary.{key}"] = value
            n = len(self.rows.t)
            level = WARN if self.warnings else OK
            values["warnings"] = "; ".join(self.warnings)
            return (
                level,
                f"done: {n} centreline samples written to {self.settings['output']}",
                values,
            )
        pct = "" if fraction is None else f" {100.0 * fraction:.0f} %"
        return OK, f"smoothing{pct} ({stage})", values

    def diagnostics(self, stamp: float) -> Any:
        """diagnostic_msgs/DiagnosticArray of the job (stamp: s, ROS clock)."""
        level, message, values = self.health()
        return rosmsg.diagnostics_to_msg(
            self.types, stamp, DIAGNOSTIC_NAME, level, message, values, hardware_id="pipe_nav"
        )


class _Told:
    """A job's pipe_nav_core.app.progress.Progress: each stage's text and the fraction of the
    current filter pass, into the job's ``stage`` and ``fraction`` (for /diagnostics)."""

    def __init__(self, job: SmootherJob) -> None:
        self.job = job

    def stage(self, text: str) -> None:
        with self.job._lock:
            self.job.stage, self.job.fraction = text, 0.0

    def fraction(self, done: float) -> None:
        with self.job._lock:
            self.job.fraction = min(max(float(done), 0.0), 1.0)
