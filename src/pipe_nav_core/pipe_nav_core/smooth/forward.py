"""One filter pass over a whole time-sorted log, as every smoothing pass runs it.

The Navigator is fed the log in up to PROGRESS_SLICES time slices, each at least SLICE_MIN_S
long, with results identical to feeding it whole: it then holds its input buffers for one
slice at a time, and after each slice the caller's Progress hears the fraction of the pass
done (a slice costs about a millisecond of Python).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.app.progress import QUIET, Progress
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.navigator import Navigator, PassOptions
from pipe_nav_core.memory import trim_heap
from pipe_nav_core.model.state import NavState
from pipe_nav_core.smooth.logs import let_go, slice_log
from pipe_nav_core.smooth.recording import SAMPLE_SPACING_S
from pipe_nav_core.types import SensorLog

Array = NDArray[np.float64]
PROGRESS_SLICES = 40  # at most this many slices a pass
SLICE_MIN_S = 60.0  # s of data: the shortest slice


def run_forward(
    log: SensorLog,
    config: NavConfig,
    *,
    initial: NavState | None = None,
    reverse: bool = False,
    epoch_times: Array | None = None,
    odometer_exclude: Array | None = None,
    reference: Array | None = None,
    initial_azimuth: float | None = None,
    record: bool = True,
    free_heading: bool | None = None,
    straight: tuple[Array, Array] | None = None,
    progress: Progress = QUIET,
    release: bool = False,
) -> Navigator:
    """One filter pass over a time-sorted log, recorded for the smoothers unless record=False;
    the other arguments are :class:`~pipe_nav_core.filter.navigator.PassOptions`' (reference: flat
    states (K, SV_SIZE) to linearize about). ``progress`` hears the fraction of the pass done;
    ``release``: the memory of log samples mapped from a file (:func:`.logs.map_imu`) is let
    go of slice by slice, once the navigator has copied them.
    ValueError when the log gives no navigation solution."""
    nav = Navigator(
        config,
        log.markers,
        PassOptions(
            record=record,
            emit=False,
            reverse=reverse,
            initial=initial,
            epoch_times=epoch_times,
            odometer_exclude=odometer_exclude,
            reference=reference,
            initial_azimuth=initial_azimuth,
            free_heading=free_heading,
            straight=straight,
        ),
    )
    feed(nav, log, config, progress=progress, release=release)
    if nav.state is None:
        raise ValueError("no navigation solution: the log has no usable IMU data after alignment")
    return nav


def feed(
    nav: Navigator,
    log: SensorLog,
    config: NavConfig,
    *,
    progress: Progress = QUIET,
    release: bool = False,
) -> None:
    """Run a Navigator over a whole time-sorted log in time slices (the module docstring), its
    recording (if any) reserved for the pass's expected counts up front and trimmed after;
    ``release``: the memory of log samples mapped from a file is let go of slice by slice
    (fed whole, a navigator copies every sample at once: at 100 km 0.6 GB, beside the 0.6 GB
    of the mapped samples read), and the heap trimmed after (:func:`memory.trim_heap`)."""
    if nav.recording is not None and len(log.imu) >= 2:
        nav.recording.reserve(*expected_counts(log, config))
    if len(log.imu) < 2:
        nav.run(log)
    else:
        span = float(log.imu.t[-1] - log.imu.t[0])
        slices = int(np.clip(math.ceil(span / SLICE_MIN_S), 1, PROGRESS_SLICES))
        edges = np.linspace(log.imu.t[0], log.imu.t[-1], slices + 1)
        for i in range(slices):
            last = i == slices - 1
            nav.run(slice_log(log, edges[i], math.inf if last else edges[i + 1]), final=last)
            progress.fraction((i + 1) / slices)
            if release:  # the navigator has copied the slice's samples
                let_go(log.imu, edges[i + 1])
    if nav.recording is not None:
        nav.recording.trim()
    if release:  # a whole-run pass: what it freed (its batches, the log's slices) goes back
        trim_heap(len(log.imu))  # (not after the heading search's short passes: the live node runs
        # them at its re-anchoring, where a collection would stall it)


def expected_counts(log: SensorLog, config: NavConfig) -> tuple[int, int]:
    """The epochs and the kept per-sample nominal rows (Recording.add_blocks) a pass over the
    log is expected to record: an epoch per filter period and per marker, and of the IMU
    samples one per SAMPLE_SPACING_S (a few percent over, so that the arrays need not grow;
    where a pass has more, they grow)."""
    t = log.imu.t
    span = float(t[-1] - t[0])
    epochs = int(1.02 * span * config.filter_rate_hz) + len(log.markers) + 16
    dt = float(np.median(np.diff(t[: 1 << 12])))
    every = max(1, int(SAMPLE_SPACING_S / dt + 1e-6)) if SAMPLE_SPACING_S > 0 and dt > 0 else 1
    return epochs, int(1.02 * len(t) / every) + 16
