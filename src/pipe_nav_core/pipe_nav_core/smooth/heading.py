"""The initial heading of the smoothing passes, found from the markers.

With the heading from the markers, the live filter starts on the bearing between the first
two markers and re-anchors at the second one by rotating its state about the first (seed
000). On a winding pipe the bearing can be 90 degrees off the initial heading, and a filter
that far off gets its heading wrong on the way (an industrial gyro resolves the Earth rate,
which it then compensates in the wrong axes), so that rotation is not the initial heading's
error. The initial heading is therefore found by odometer dead reckoning over the data up to
the second marker, where nothing but the gyros turns the heading and the re-anchoring
rotation is the initial heading's error; repeated (secant) until the rotation is below
ANCHOR_RAD.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipe_nav_core.app.progress import QUIET, Progress
from pipe_nav_core.config import NavConfig
from pipe_nav_core.faults.odometer import bridged_for_dead_reckoning
from pipe_nav_core.filter.navigator import Navigator
from pipe_nav_core.smooth.forward import run_forward
from pipe_nav_core.smooth.logs import log_until
from pipe_nav_core.types import SensorLog, markers_sorted

ANCHOR_RAD = 5e-4  # rad: re-anchoring rotation below which the initial heading is settled
ANCHOR_PASSES = 6  # at most this many re-anchoring passes over the data up to the 2nd marker
# prior sigma of the dead-reckoned initial heading (gyro drift and scale factor over the bends
# up to the second marker); the markers' own constraint on the heading is some 1e-4 rad, so
# the prior hardly counts there, but it keeps the forward pass from trading a heading it
# thinks unknown for small tilt discrepancies through the Earth rate
ANCHORED_HEADING_SIGMA = np.radians(5.0)
PAST_SECOND_MARKER_S = 1.0  # s of data after the second marker that the search runs over


def smoothing_config(
    log: SensorLog, config: NavConfig, progress: Progress = QUIET, *, reverse: bool = False
) -> NavConfig:
    """The configuration of the smoothing passes over a time-sorted log: with the heading from
    the markers and at least two of them, the live filter up to the second marker and then
    :func:`anchored_config` from it; otherwise ``config`` itself."""
    markers = markers_sorted(log.markers)
    if config.heading_source != "markers" or len(markers) < 2:
        return config
    # the live filter up to the second marker is all the re-anchoring needs
    progress.stage("forward filter up to the second marker")
    head = log_until(log, markers[1].t + PAST_SECOND_MARKER_S)
    live = run_forward(head, config, record=False, reverse=reverse, progress=progress)
    return anchored_config(log, config, live, progress, reverse=reverse)


def anchored_config(
    log: SensorLog,
    config: NavConfig,
    live: Navigator,
    progress: Progress = QUIET,
    *,
    reverse: bool = False,
) -> NavConfig:
    """``config`` with the initial heading found by dead reckoning (see the module) from the
    live filter ``live``'s start and re-anchoring, as a fixed heading with
    ANCHORED_HEADING_SIGMA (or the configured initial heading sigma if smaller) as its prior.
    ``config`` itself unless the heading is from the markers and ``live`` found one."""
    if config.heading_source != "markers" or live.initial_azimuth is None:
        return config
    az = live.initial_azimuth
    markers = markers_sorted(log.markers)
    if len(markers) >= 2 and live.reanchor_rad != 0.0:
        head = bridged_for_dead_reckoning(log_until(log, markers[1].t + PAST_SECOND_MARKER_S))
        dr = replace(config, mode="dr")

        # secant iteration on f(azimuth) = the rotation the re-anchoring asks for
        def rotation(azimuth: float) -> float:
            nav = run_forward(head, dr, initial_azimuth=azimuth, record=False, reverse=reverse,
                              progress=progress)  # fmt: skip
            return nav.reanchor_rad

        az_prev, f_prev = az, rotation(az)
        az = az + f_prev
        for i in range(ANCHOR_PASSES):
            progress.stage(f"re-anchoring the initial heading (pass {i + 1})")
            f = rotation(az)
            if abs(f) < ANCHOR_RAD:
                az += f
                break
            slope = (f - f_prev) / (az - az_prev) if az != az_prev else -1.0
            az_prev, f_prev = az, f
            az = az - f / slope if -2.0 < slope < -0.25 else az + f
    return replace(
        config,
        heading_source="fixed",
        initial_azimuth=float(np.mod(az, 2 * np.pi)),
        initial_heading_sigma=min(config.initial_heading_sigma, ANCHORED_HEADING_SIGMA),
    )
