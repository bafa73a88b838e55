"""Offline smoothing of a whole run: the passes over the log and the method that smooths each.

Methods (``method``):
- ``forward``: the forward filter alone (what the live node sees);
- ``rts``: Rauch-Tung-Striebel over the recorded forward filter (:mod:`.rts`);
- ``two-filter``: the forward filter fused with a filter run on the time-reversed data
  (:mod:`.two_filter`); from the second pass on the two run at once, on two cores (the
  backward filter takes its epochs and its initial heading from the reference trajectory);
- ``graph``: the batch (factor-graph) smoother (:mod:`pipe_nav_core.graph`): Gauss-Newton over
  the whole run with a robust loss on the markers, started from the ``rts`` result.

Passes:
1. with the heading from the markers, the live filter up to the second marker and the
   dead-reckoned initial heading found from it (:mod:`.heading`);
2. a filter pass over the whole log from that heading (else the live filter's configuration):
   its estimates are ``forward`` of the result;
3. Gauss-Newton: each following pass is linearized about the previous pass's smoothed
   trajectory, every epoch of it (:class:`pipe_nav_core.filter.navigator.PassOptions`
   ``reference``), with
   the same prior, so that the smoother converges to the optimum of the whole batch problem
   (a factor graph of the prior, the IMU transitions between epochs and every update) instead
   of the optimum of a linearization about a drifting forward filter; it stops when a pass's
   attitude step is below CONVERGED_RAD (or after MAX_PASSES). Odometer epochs that disagree
   with the previous pass's smoothed path (wheel slip, :mod:`.slips`) are left out of the next
   pass.

Every filter pass tells the caller's Progress the fraction of it done (:mod:`.forward`), and
each stage is named as it begins.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.app.progress import QUIET, Progress
from pipe_nav_core.background import Background
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.navigator import Navigator
from pipe_nav_core.memory import trim_heap
from pipe_nav_core.model.measurements.straight_pipe import Sections, sections
from pipe_nav_core.model.state import (
    SV_DIST,
    SV_H,
    SV_LAT,
    SV_LON,
    SV_T,
    Layout,
    inject_many,
    layout_for,
)
from pipe_nav_core.smooth.centreline import (
    Parked,
    SmoothResult,
    forward_trajectory,
    marker_residuals,
    smoothed_centreline,
    summarize,
    with_free_heading,
)
from pipe_nav_core.smooth.chunks import drop_spare
from pipe_nav_core.smooth.forward import run_forward
from pipe_nav_core.smooth.heading import smoothing_config
from pipe_nav_core.smooth.logs import let_go, map_imu
from pipe_nav_core.smooth.methods import DEFAULT_METHOD, MAX_PASSES, METHODS
from pipe_nav_core.smooth.recording import Recording
from pipe_nav_core.smooth.rts import rts_packed
from pipe_nav_core.smooth.slips import find_slips
from pipe_nav_core.smooth.two_filter import (
    backward_pass,
    backward_sections,
    end_azimuth,
    fuse_passes,
    two_filter,
)
from pipe_nav_core.types import Datum, SensorLog, Trajectory, markers_sorted

if TYPE_CHECKING:
    from pipe_nav_core.smooth.ahead import FirstPassAhead

Array = NDArray[np.float64]
# A pass linearized within this attitude of its smoothed result has converged. What is
# nonlinear in the problem is the attitude (the position enters through the gravity and
# Earth-rate models, which do not change over metres), and Gauss-Newton converges
# quadratically in it: measured on the bench's scenarios, after a pass whose attitude step was
# under 0.4 mrad the next pass moved the centreline by at most 2 mm (0.1 mm on the 10 km
# lines, whose second pass moves metres of position at 0.03-0.7 mrad).
CONVERGED_RAD = 3e-4  # rad: largest attitude step of a converged pass
# the methods whose passes take NavConfig.smoothing_rate_hz's epochs (the others the live
# filter's): two-filter's backward filter lost 1.5 cm (7 %) on the sparse 10 km line at 2.5 Hz
LONG_EPOCH_METHODS = ("rts", "graph")
EPOCH_BATCH = 1 << 16  # epochs corrected at once (bounds the temporaries at 100 km)


def smooth_log(
    log: SensorLog,
    config: NavConfig,
    *,
    method: str = DEFAULT_METHOD,
    iterations: int = MAX_PASSES,
    progress: Progress = QUIET,
    reverse: bool = False,
    ahead: FirstPassAhead | None = None,
) -> SmoothResult:
    """Smooth a whole time-sorted log (IMU in imu_link as recorded) and return the centreline.
    ``reverse``: the log is a run in reversed time (:func:`.logs.reverse_log`: a segment that
    ends at rest, aligned at its end); every pass then turns the Earth the other way
    (Navigator reverse). ``progress`` is told each stage and the fraction of each filter pass
    done.

    Passes (see the module docstring): with the heading from the markers, the live filter up
    to the second marker and the search for the dead-reckoned initial heading; a filter pass
    over the whole log (from that heading, else the live filter: its estimates are
    ``forward``); then up to ``iterations`` smoothing passes, each linearized
    about the previous smoothed trajectory (Gauss-Newton), until the attitude step is below
    CONVERGED_RAD (the odometer epochs a converged pass's centreline finds slipping are those
    of the pass before: it has moved by millimetres; on every bench scenario the same set).
    The summary says how many
    passes ran (``passes_run``), which was taken (``passes``), whether they converged
    (``converged``) and the taken pass's position and attitude steps (``last_step_m``,
    ``last_step_rad``).
    ``graph``: those passes with RTS, then the batch smoother from their last smoothed
    trajectory, with their odometer exclusions (:func:`_graph_result`).
    ``ahead``: the heading search and first pass run while the bag was read, taken where they
    are this log's (:class:`.ahead.FirstPassAhead`).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if reverse and method == "two-filter":
        method = "rts"  # its backward filter would run forward in time: the same as rts here
    if len(log.imu) < 10:
        raise ValueError("the log has fewer than 10 IMU samples")
    map_imu(log.imu)  # read from a file: each filter pass lets go of what it has read
    say = progress.stage
    layout = layout_for(config)
    markers = markers_sorted(log.markers)
    cfg = epochs = epoch_config(config, method)
    taken = ahead.take(log, epochs, method, reverse) if ahead is not None else None
    if taken is not None:  # the same pass, run while the bag was read
        cfg, nav = taken
        say("forward filter (run while the bag was read)")
        let_go(log.imu)  # as after run_forward's own pass: nothing of the log is in memory
        trim_heap(len(log.imu))  # for it, and what the pass freed
    else:
        if method != "forward":
            cfg = smoothing_config(log, cfg, progress, reverse=reverse)
        say("forward filter" if cfg is epochs else "forward filter (re-anchored heading)")
        nav = run_forward(log, cfg, reverse=reverse, progress=progress, release=True)
    assert nav.recording is not None
    lost_at = nav.after_odometer_loss
    if lost_at and cfg.filter_rate_hz < config.filter_rate_hz:
        # the long epochs' first pass lost the wheel somewhere (after an attitude turn no gyro
        # sample saw: a shock that saturates the gyro; the 100 km line's simulator did so
        # until 0d6d5dc, and smoothed it 0.5 m off in height with a 5 cm sigma): the whole run
        # is smoothed again with the live filter's epochs
        say(f"the {cfg.filter_rate_hz:g} Hz epochs lost the odometer before {lost_at[0]}: "
            f"smoothing at {config.filter_rate_hz:g} Hz")  # fmt: skip
        nav.recording.close()  # its chunk arrays go to the next pass's recording
        del nav
        short = replace(config, smoother_rate_hz=config.filter_rate_hz)
        result = smooth_log(log, short, method=method, iterations=iterations,
                            progress=progress, reverse=reverse)  # fmt: skip
        result.summary["long_epochs_lost_odometer"] = lost_at
        return result
    forward = with_free_heading(forward_trajectory(nav.recording), nav.free_heading)
    first = nav.recording.states[0].copy()  # a view would keep every pass-1 state alive
    datum = nav.datum or Datum(float(first[SV_LAT]), float(first[SV_LON]), float(first[SV_H]))

    def result_of(nav: Navigator, centre: Trajectory) -> SmoothResult:
        centre = with_free_heading(centre, nav.free_heading)
        result = SmoothResult(
            centre,
            forward,
            datum,
            markers,
            marker_residuals(centre, markers),
            config=config,
        )
        result.summary = summarize(result, nav)
        result.summary["epoch_rate_hz"] = nav.cfg.filter_rate_hz
        return result

    if method == "forward":
        rec = nav.recording
        e = np.zeros((len(rec), len(rec.pose)))
        result = result_of(nav, smoothed_centreline(rec, e, rec.pose_variances()))
        result.summary.update(passes=1, passes_run=1)
        return result
    exclude: Array | None = None
    reference: Array | None = None
    straight: Sections | None = None  # each pass's, its gentle curves kept for the next
    arw = nav.imu_spec.gyro_arw  # rad/sqrt(s): the IMU model the first pass chose
    best: tuple[int, SmoothResult | Parked] | None = None  # the pass taken so far
    n_pass = max(1, iterations)
    for it in range(n_pass):
        back: Background | None = None
        if it:
            straight = sections(reference, cfg, arw, straight.curves if straight else None)
            if method == "two-filter":  # its backward half on the other core
                end = float(reference[-1, SV_DIST])
                back = Background("pipe-nav backward filter", backward_pass, log, cfg,
                                  reference[:, SV_T].copy(), end_azimuth(reference[-1]),
                                  exclude, QUIET, backward_sections(straight[:2], end))  # fmt: skip
            say(f"forward filter about the smoothed trajectory (pass {it + 1})"
                + (", the backward filter beside it" if back else ""))  # fmt: skip
            nav = run_forward(log, cfg, reference=reference, odometer_exclude=exclude,
                              reverse=reverse, progress=progress, release=True,
                              straight=(straight.plan, straight.vertical))  # fmt: skip
        rec = nav.recording
        assert rec is not None
        if method in ("rts", "graph"):
            say(f"RTS smoother (pass {it + 1})")
            e, var = rts_packed(rec.rts_chunks(), rec.dx, rec.format, var_cols=rec.pose)
        else:
            say(f"backward filter (pass {it + 1})")
            if back is None:
                e, var = two_filter(log, cfg, rec, layout, exclude, progress, rec.pose)
            else:
                e, var = fuse_passes(rec, back.result(), layout, rec.pose)
        rec.close()  # the covariances are no longer needed
        # a pass that rejects more markers than an earlier one is not taken; the one it
        # replaces is let go before its centreline is built, so that two are never held
        rejected = int(nav.diagnostics().get("rejected_marker", 0))
        if best is not None and rejected <= best[0]:
            best = None
        step_pos, step_att = step_size(rec, e, layout)
        converged = reference is not None and step_att < CONVERGED_RAD
        last = converged or it == n_pass - 1
        if last:  # the spare chunk arrays wait for a next pass's recording: there is none
            drop_spare()
        e_pose = e[:, rec.pose]
        if last and method != "graph":  # only its centreline is left to make (no next
            del e  # reference, no slips): what that reads is kept
            rec.keep_for_centreline()
        centre = smoothed_centreline(rec, e_pose, var)
        result = result_of(nav, centre)
        result.summary["passes"] = it + 1
        if best is None or rejected <= best[0]:
            best = (rejected, result)
        result.summary["last_step_m"] = step_pos
        result.summary["last_step_rad"] = step_att
        result.summary["gentle_curves_m"] = curve_length(straight)
        # the slips the next pass leaves out (after the last pass only the graph takes them)
        new_exclude = (
            find_slips(rec, centre, cfg, resolution=nav.odometer_resolution)
            if layout.has_vel and (not last or method == "graph")
            else None
        )
        if last:
            if method == "graph":  # the batch smoother, from this pass's smoothed trajectory
                start = smoothed_states(rec, e, layout)
                slips = new_exclude if new_exclude is not None else exclude
                straight = sections(start, cfg, arw, straight.curves if straight else None)
                del nav, rec, e, var, centre, result, best  # the RTS passes' memory first
                return _graph_result(log, cfg, start, slips, it + 1, progress, reverse, result_of,
                                     straight)  # fmt: skip
            break
        del centre, result, var  # the pass kept so far holds its centreline ...
        if isinstance(best[1], SmoothResult) and Parked.worth(best[1]):
            best = (best[0], Parked(best[1]))  # ... on disk while the next pass runs
        reference = smoothed_states(rec, e, layout)
        exclude = new_exclude
        del nav, rec, e  # free this pass before the next
    assert best is not None
    taken = best[1].restore() if isinstance(best[1], Parked) else best[1]
    taken.summary["passes_run"] = it + 1
    taken.summary["converged"] = converged
    return taken


def curve_length(straight: Sections | None) -> float:
    """The length (m) of the gentle curves a pass's straight sections leave out, in plan and
    in the vertical plane together (:func:`.straight_pipe.sections`)."""
    if straight is None:
        return 0.0
    return float(sum((c[:, 1] - c[:, 0]).sum() for c in straight.curves))


def epoch_config(config: NavConfig, method: str) -> NavConfig:
    """The settings of ``method``'s passes before the heading search: the smoothing epochs
    (NavConfig.smoothing_rate_hz) for LONG_EPOCH_METHODS, else ``config``'s own."""
    if method in LONG_EPOCH_METHODS:
        return replace(config, filter_rate_hz=config.smoothing_rate_hz())
    return config


def _graph_result(
    log: SensorLog,
    cfg: NavConfig,
    start: Array,
    exclude: Array | None,
    rts_passes: int,
    progress: Progress,
    reverse: bool,
    result_of: Callable[[Navigator, Trajectory], SmoothResult],
    straight: Sections,
) -> SmoothResult:
    """The batch smoother (pipe_nav_core.graph) from the RTS passes' last smoothed trajectory
    (flat states start (K, SV_SIZE)) with their odometer exclusions and the straight sections
    of start; the summary says the method, the RTS passes and the graph's iterations, markers
    downweighted by its robust loss and factors left out by its gate. ``progress`` hears its
    stages."""
    from pipe_nav_core.graph import graph_smooth

    g = graph_smooth(log, cfg, start, odometer_exclude=exclude, reverse=reverse,
                     say=progress.stage, straight=(straight.plan, straight.vertical))  # fmt: skip
    nav, rec = g.nav, g.nav.recording
    assert rec is not None
    e, var = g.corrections(), g.solution.var[:, rec.pose]
    summary = dict(
        method="graph",
        passes=rts_passes,
        passes_run=rts_passes,
        graph_iterations=g.iterations,
        graph_converged=g.converged,
        graph_cost=g.history[-1],
        graph_markers_downweighted=list(g.weighing.downweighted),
        graph_factors_gated=dict(g.weighing.gated),
        gentle_curves_m=curve_length(straight),
    )
    del g  # its solution and final states (0.5 GB at 100 km) before the centreline is made
    centre = smoothed_centreline(rec, e, var)
    rec.close()
    result = result_of(nav, centre)
    result.summary.update(summary)
    return result


def smoothed_states(rec: Recording, e: Array, layout: Layout) -> Array:
    """The smoothed state of every epoch, flat (K, SV_SIZE): lin[k] (+) (x_upd[k] + e[k])
    (in batches of EPOCH_BATCH epochs: bounded temporaries)."""
    lin, x_upd = rec.lin, rec.x_upd
    out = np.empty((len(e), lin.shape[1]))
    for b in range(0, len(e), EPOCH_BATCH):
        s = slice(b, b + EPOCH_BATCH)
        out[s] = inject_many(lin[s], x_upd[s] + e[s], layout)
    return out


def step_size(rec: Recording, e: Array, layout: Layout) -> tuple[float, float]:
    """Largest smoothed correction of the position (m) and attitude (rad) relative to the
    pass's linearization points: the Gauss-Newton step of that pass."""
    x_upd = rec.x_upd
    pos = att_ = 0.0
    for b in range(0, len(e), EPOCH_BATCH):
        s = slice(b, b + EPOCH_BATCH)
        d = x_upd[s] + e[s]
        pos = max(pos, float(np.max(np.linalg.norm(d[:, layout.pos], axis=1))))
        att_ = max(att_, float(np.max(np.linalg.norm(d[:, layout.att], axis=1))))
    return pos, att_
