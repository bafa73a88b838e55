"""Offline smoothing of a whole run: forward filter, then RTS or two-filter fusion, with a
re-linearization pass, and the smoothed centreline at the IMU rate.

Methods (``method``):
- ``forward``: the forward filter alone (what the live node sees);
- ``rts``: Rauch-Tung-Striebel over the recorded forward filter;
- ``two-filter``: the forward filter fused with a filter run on the time-reversed data
  (seed 001 RTS-FC, seed 004);
- ``graph``: the batch (factor-graph) smoother (:mod:`pipe_nav_core.graph`): Gauss-Newton over
  the whole run with a robust loss on the markers, started from the ``rts`` result.

Passes:
1. the live filter (what the live node computes; ``forward`` of the result unless 2.; with
   the heading from the markers it runs only up to the second marker, which is all 2. needs);
2. with the heading from the markers, the initial heading is found by odometer dead
   reckoning up to the second marker, re-anchored until it no longer turns
   (:func:`anchored_config`), and a filter pass starts from it (``forward`` of the result);
3. Gauss-Newton: each following pass is linearized about the previous pass's smoothed
   trajectory, every epoch of it (:class:`pipe_nav_core.navigator.PassOptions` ``reference``), with
   the same prior, so that the smoother converges to the optimum of the whole batch problem
   (a factor graph of the prior, the IMU transitions between epochs and every update) instead
   of the optimum of a linearization about a drifting forward filter; it stops when a pass's
   step is below CONVERGED_POS_M and CONVERGED_RAD. Odometer epochs that disagree with the
   previous pass's smoothed path (wheel slip) are left out of the next pass.
"""

from __future__ import annotations

import contextvars
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from . import attitude as att
from . import earth
from .anchoring import FreeHeading
from .config import NOISE_EPOCH_S, NavConfig
from .navigator import Navigator, PassOptions
from .odometer_faults import bridged_for_dead_reckoning
from .recording import Recording
from .smoothing import rts_packed
from .state import (
    SV_BG,
    SV_DIST,
    SV_H,
    SV_K,
    SV_LAT,
    SV_LON,
    SV_Q,
    SV_T,
    SV_VEL,
    Layout,
    NavState,
    difference_many,
    inject_many,
    layout_for,
)
from .types import (
    Datum,
    ImuSamples,
    MagSamples,
    Marker,
    OdometerSamples,
    SensorLog,
    Trajectory,
    markers_sorted,
)

if TYPE_CHECKING:
    from .products import IntegrityReport
    from .products.welds import Weld

Array = NDArray[np.float64]
METHODS = ("forward", "rts", "two-filter", "graph")
# A pass linearized within these of its smoothed result has converged: Gauss-Newton converges
# quadratically here (a 0.1 m step is followed by about 2 mm, a 2 mm one by microns), so the
# result of such a pass is the optimum to well below a millimetre.
CONVERGED_RAD = 1e-4  # rad: largest attitude step of a converged pass
CONVERGED_POS_M = 0.01  # m: largest position step of a converged pass
ANCHOR_RAD = 5e-4  # rad: re-anchoring rotation below which the initial heading is settled
ANCHOR_PASSES = 6  # at most this many re-anchoring passes over the data up to the 2nd marker
# prior sigma of the dead-reckoned initial heading (gyro drift and scale factor over the bends
# up to the second marker); the markers' own constraint on the heading is some 1e-4 rad, so
# the prior hardly counts there, but it keeps the forward pass from trading a heading it
# thinks unknown for small tilt discrepancies through the Earth rate
ANCHORED_HEADING_SIGMA = np.radians(5.0)


@dataclass
class SmoothResult:
    """Result of :func:`smooth_log`.

    centreline: smoothed trajectory at the IMU sample times (sigma_enu filled);
    forward: forward-filter estimates per epoch (what /pipe_nav/odometry carries);
    datum: origin of map (first marker); markers: the markers used;
    marker_residuals: name -> (3,) ENU m, smoothed position minus survey at the passage;
    summary: figures for people (see :func:`summarize`); config: the settings the run was
    smoothed with (the IMU model chosen for it); products: its integrity products, when the
    pipeline computed them (products.integrity_report); welds: its girth welds
    (products.welds.detect_welds), None when the pipeline did not look (no magnetometer).
    """

    centreline: Trajectory
    forward: Trajectory
    datum: Datum
    markers: list[Marker]
    marker_residuals: dict[str, Array]
    summary: dict[str, object] = field(default_factory=dict)
    config: NavConfig | None = None
    products: IntegrityReport | None = None
    welds: list[Weld] | None = None


def reverse_log(log: SensorLog) -> SensorLog:
    """The log in reversed time (t -> -t): IMU sample i (the mean over (t[i-1], t[i]]) becomes
    a sample stamped -t[i-1] with negated rate; odometer speed negated; markers re-stamped."""
    imu = log.imu
    t = -imu.t[:-1][::-1]
    rimu = ImuSamples(t, -imu.gyro[1:][::-1], imu.accel[1:][::-1])
    o = log.odometer
    rodo = OdometerSamples(-o.t[::-1], o.distance[::-1], -o.speed[::-1])
    m = log.mag
    rmag = MagSamples(-m.t[::-1], m.field[::-1])
    markers = [
        Marker(k.name, -k.t, k.lat, k.lon, k.alt, k.sigma_enu)
        for k in markers_sorted(log.markers)[::-1]
    ]
    return SensorLog(rimu, rodo, rmag, markers)


def _flip(layout: Layout) -> Array:
    """Signs mapping reversed-time error states to forward ones (velocity, gyro bias negate)."""
    s = np.ones(layout.n)
    if layout.vel is not None:
        s[layout.vel] = -1.0
    s[layout.bg] = -1.0
    return s


# a forward pass feeds the log to the engine in up to this many time slices, each at least
# SLICE_MIN_S long (identical results): the engine holds its input buffers for one slice at a
# time, and a caller can show the progress; a slice costs about a millisecond of Python
PROGRESS_SLICES = 40
SLICE_MIN_S = 60.0  # s of data
# receives the fraction (0..1) of each forward pass done, while a caller shows progress
_FRACTION: contextvars.ContextVar[Callable[[float], None] | None] = contextvars.ContextVar(
    "pipe_nav_fraction", default=None
)


def slice_log(log: SensorLog, t0: float, t1: float) -> SensorLog:
    """The samples and markers of a time-sorted log with stamps in [t0, t1), s."""

    def sel(t: Array) -> slice:
        return slice(int(np.searchsorted(t, t0, "left")), int(np.searchsorted(t, t1, "left")))

    return SensorLog(
        log.imu.slice(sel(log.imu.t)),
        log.odometer.slice(sel(log.odometer.t)),
        log.mag.slice(sel(log.mag.t)),
        [m for m in log.markers if t0 <= m.t < t1],
    )


def report_fraction(callback: Callable[[float], None] | None) -> contextvars.Token:
    """Make forward passes report the fraction done to callback (until reset_fraction)."""
    return _FRACTION.set(callback)


def reset_fraction(token: contextvars.Token) -> None:
    """Undo report_fraction."""
    _FRACTION.reset(token)


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
) -> Navigator:
    """One filter pass over a time-sorted log (recorded for the smoothers unless record=False;
    reference: flat states (K, SV_SIZE), free_heading: see PassOptions)."""
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
        ),
    )
    report = _FRACTION.get()
    if len(log.imu) < 2:
        nav.run(log)
    else:
        span = float(log.imu.t[-1] - log.imu.t[0])
        slices = int(np.clip(math.ceil(span / SLICE_MIN_S), 1, PROGRESS_SLICES))
        edges = np.linspace(log.imu.t[0], log.imu.t[-1], slices + 1)
        for i in range(slices):
            last = i == slices - 1
            nav.run(slice_log(log, edges[i], math.inf if last else edges[i + 1]), final=last)
            if report is not None:
                report((i + 1) / slices)
    if nav.state is None:
        raise ValueError("no navigation solution: the log has no usable IMU data after alignment")
    return nav


def smooth_log(
    log: SensorLog,
    config: NavConfig,
    *,
    method: str = "rts",
    iterations: int = 5,
    progress: Callable[[str], None] | None = None,
    reverse: bool = False,
) -> SmoothResult:
    """Smooth a whole time-sorted log (IMU in imu_link as recorded) and return the centreline.
    ``reverse``: the log is a run in reversed time (reverse_log: a segment that ends at rest,
    aligned at its end); every pass then turns the Earth the other way (Navigator reverse).

    Passes (see the module docstring): with the heading from the markers, the live filter up
    to the second marker and the search for the dead-reckoned initial heading; a filter pass
    over the whole log (from that heading, else the live filter: its estimates are
    ``forward``); then up to ``iterations`` smoothing passes, each linearized
    about the previous smoothed trajectory (Gauss-Newton), until the step is below
    CONVERGED_POS_M and CONVERGED_RAD and the excluded odometer epochs do not change.
    ``graph``: those passes with RTS, then the batch smoother from their last smoothed
    trajectory, with their odometer exclusions (:func:`_graph_result`).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if reverse and method == "two-filter":
        method = "rts"  # its backward filter would run forward in time: the same as rts here
    if len(log.imu) < 10:
        raise ValueError("the log has fewer than 10 IMU samples")
    say = progress or (lambda _msg: None)
    layout = layout_for(config)
    markers = markers_sorted(log.markers)
    cfg = config
    if method != "forward" and config.heading_source == "markers" and len(markers) >= 2:
        # the live filter up to the second marker is all the re-anchoring needs
        say("forward filter up to the second marker")
        head = run_forward(_truncate(log, markers[1].t + 1.0), config, record=False,
                           reverse=reverse)  # fmt: skip
        cfg = anchored_config(log, config, head, say, reverse=reverse)
    say("forward filter" if cfg is config else "forward filter (re-anchored heading)")
    nav = run_forward(log, cfg, reverse=reverse)
    assert nav.recording is not None
    forward = _with_free_heading(_forward_trajectory(nav.recording), nav.free_heading)
    first = nav.recording.states[0]
    datum = nav.datum or Datum(float(first[SV_LAT]), float(first[SV_LON]), float(first[SV_H]))

    def result_of(nav: Navigator, centre: Trajectory) -> SmoothResult:
        centre = _with_free_heading(centre, nav.free_heading)
        result = SmoothResult(
            centre, forward, datum, markers, marker_residuals(centre, markers),
            config=config,
        )
        result.summary = summarize(result, nav)
        return result

    if method == "forward":
        rec = nav.recording
        e = np.zeros((len(rec), layout.n))
        result = result_of(nav, _centreline(rec, e, rec.variances(), layout))
        result.summary.update(passes=1, passes_run=1)
        return result
    exclude: Array | None = None
    reference: Array | None = None
    best: tuple[int, SmoothResult] | None = None
    n_pass = max(1, iterations)
    for it in range(n_pass):
        if it:
            say(f"forward filter about the smoothed trajectory (pass {it + 1})")
            nav = run_forward(log, cfg, reference=reference, odometer_exclude=exclude,
                              reverse=reverse)  # fmt: skip
        rec = nav.recording
        assert rec is not None
        if method in ("rts", "graph"):
            say(f"RTS smoother (pass {it + 1})")
            e, var = rts_packed(rec.rts_chunks(), rec.dx, rec.format)
        else:
            say(f"backward filter (pass {it + 1})")
            e, var = _two_filter(log, cfg, rec, layout, exclude)
        rec.close()  # the covariances are no longer needed
        centre = _centreline(rec, e, var, layout)
        result = result_of(nav, centre)
        result.summary["passes"] = it + 1
        # a pass that rejects more markers than an earlier one is not taken
        rejected = int(result.summary["markers_rejected"])
        if best is None or rejected <= best[0]:
            best = (rejected, result)
        step_pos, step_att = step_size(rec, e, layout)
        result.summary["last_step_m"] = step_pos
        # the slips the next pass leaves out (after the last pass only the graph takes them)
        wanted = it < n_pass - 1 or method == "graph"
        new_exclude = (
            find_slips(rec, centre, cfg, resolution=nav.odometer_resolution)
            if layout.has_vel and wanted
            else None
        )
        same_slips = new_exclude is None or (
            exclude is not None and np.array_equal(exclude, new_exclude)
        )
        converged = (
            reference is not None
            and step_pos < CONVERGED_POS_M
            and step_att < CONVERGED_RAD
            and same_slips
        )
        if converged or it == n_pass - 1:
            if method == "graph":  # the batch smoother, from this pass's smoothed trajectory
                start = smoothed_states(rec, e, layout)
                slips = new_exclude if new_exclude is not None else exclude
                del nav, rec, e, var, centre, result, best  # the RTS passes' memory first
                return _graph_result(log, cfg, start, slips, it + 1, say, reverse, result_of)
            break
        reference = smoothed_states(rec, e, layout)
        exclude = new_exclude
        del nav, rec, e, var, centre, result  # free this pass before the next
    assert best is not None
    best[1].summary["passes_run"] = it + 1
    return best[1]


def _graph_result(
    log: SensorLog,
    cfg: NavConfig,
    start: Array,
    exclude: Array | None,
    rts_passes: int,
    say: Callable[[str], None],
    reverse: bool,
    result_of: Callable[[Navigator, Trajectory], SmoothResult],
) -> SmoothResult:
    """The batch smoother (pipe_nav_core.graph) from the RTS passes' last smoothed trajectory
    (flat states start (K, SV_SIZE)) with their odometer exclusions; the summary says the
    method, the RTS passes and the graph's iterations, markers downweighted by its robust
    loss and factors left out by its gate."""
    from .graph import graph_smooth

    g = graph_smooth(log, cfg, start, odometer_exclude=exclude, reverse=reverse, say=say)
    rec = g.nav.recording
    assert rec is not None
    centre = _centreline(rec, g.corrections(), g.solution.var, layout_for(cfg))
    rec.close()
    result = result_of(g.nav, centre)
    result.summary.update(
        method="graph",
        passes=rts_passes,
        passes_run=rts_passes,
        graph_iterations=g.iterations,
        graph_converged=g.converged,
        graph_cost=g.history[-1],
        graph_markers_downweighted=list(g.weighing.downweighted),
        graph_factors_gated=dict(g.weighing.gated),
    )
    return result


def anchored_config(
    log: SensorLog,
    config: NavConfig,
    live: Navigator,
    say: Callable[[str], None] = lambda _msg: None,
    *,
    reverse: bool = False,
) -> NavConfig:
    """The configuration of the smoothing passes. With the heading from the markers, the live
    filter starts on the bearing between the first two markers and re-anchors at the second
    one by rotating its state about the first (seed 000). On a winding pipe the bearing can be
    90 degrees off the initial heading, and a filter that far off gets its heading wrong on
    the way (an industrial gyro resolves the Earth rate, which it then compensates in the
    wrong axes), so that rotation is not the initial heading's error. The initial heading is
    therefore found by odometer dead reckoning over the data up to the second marker, where
    nothing but the gyros turns the heading and the re-anchoring rotation is the initial
    heading's error; repeated (secant) until the rotation is below ANCHOR_RAD. The smoothing
    passes start from that heading, with ANCHORED_HEADING_SIGMA (or the configured initial
    heading sigma if smaller) as its prior."""
    if config.heading_source != "markers" or live.initial_azimuth is None:
        return config
    az = live.initial_azimuth
    markers = markers_sorted(log.markers)
    if len(markers) >= 2 and live.reanchor_rad != 0.0:
        head = bridged_for_dead_reckoning(_truncate(log, markers[1].t + 1.0))
        dr = replace(config, mode="dr")
        # secant iteration on f(azimuth) = the rotation the re-anchoring asks for
        def rotation(azimuth: float) -> float:
            nav = run_forward(head, dr, initial_azimuth=azimuth, record=False, reverse=reverse)
            return nav.reanchor_rad

        az_prev, f_prev = az, rotation(az)
        az = az + f_prev
        for i in range(ANCHOR_PASSES):
            say(f"re-anchoring the initial heading (pass {i + 1})")
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


def _truncate(log: SensorLog, t_end: float) -> SensorLog:
    """The log up to t_end (s)."""
    return SensorLog(
        log.imu.slice(log.imu.t <= t_end),
        log.odometer.slice(log.odometer.t <= t_end),
        log.mag.slice(log.mag.t <= t_end),
        [m for m in log.markers if m.t <= t_end],
    )


def smoothed_states(rec: Recording, e: Array, layout: Layout) -> Array:
    """The smoothed state of every epoch, flat (K, SV_SIZE): lin[k] (+) (x_upd[k] + e[k])."""
    return inject_many(rec.lin, rec.x_upd + e, layout)


def step_size(rec: Recording, e: Array, layout: Layout) -> tuple[float, float]:
    """Largest smoothed correction of the position (m) and attitude (rad) relative to the
    pass's linearization points: the Gauss-Newton step of that pass."""
    d = rec.x_upd + e
    pos = float(np.max(np.linalg.norm(d[:, layout.pos], axis=1)))
    att_ = float(np.max(np.linalg.norm(d[:, layout.att], axis=1)))
    return pos, att_


def find_slips(
    rec: Recording,
    centre: Trajectory,
    config: NavConfig,
    n_sigma: float = 4.0,
    resolution: float = 0.0,
) -> Array:
    """Epochs whose calibrated odometer distance disagrees with the smoothed path length by more
    than n_sigma sigmas of an epoch's odometer distance (wheel slip or spin), widened by one
    epoch on each side, as (N, 2) time intervals in s. The sigma combines the white speed noise
    over the epoch and the quantization of the two readings that bound it (resolution m per
    count: variance resolution^2 / 6); with a coarse encoder the latter dominates.
    centre: the centreline of rec (:func:`_centreline`, one row per recorded sample)."""
    enu = earth.geodetic_to_enu(
        centre.lat, centre.lon, centre.h, centre.lat[0], centre.lon[0], centre.h[0]
    )
    step = np.linalg.norm(np.diff(enu, axis=0, prepend=enu[:1]), axis=1)
    k = rec.s_epoch
    n_ep = len(rec)
    path = np.bincount(k, weights=step, minlength=n_ep)
    s_odo = rec.s_odo
    d_odo = np.diff(s_odo, prepend=s_odo[:1])
    scale = 1.0 + rec.states[:, SV_K]
    odo = np.bincount(k, weights=d_odo, minlength=n_ep) * scale
    t = rec.t
    T = np.diff(t, prepend=t[:1])
    white = config.odometer_speed_sigma * np.sqrt(NOISE_EPOCH_S * T)  # sigma_T * T
    sigma = np.sqrt(white**2 + resolution**2 / 6.0)
    bad = np.abs(np.abs(odo) - path) > n_sigma * np.maximum(sigma, 1e-9)
    bad[0] = False
    bad = bad | np.r_[bad[1:], False] | np.r_[False, bad[:-1]]
    idx = np.nonzero(bad)[0]
    idx = idx[idx > 0]
    return np.stack([t[idx - 1], t[idx]], axis=-1) if len(idx) else np.zeros((0, 2))


FUSE_BATCH = 1024  # epochs fused at once by the two-filter smoother


def _two_filter(
    log: SensorLog,
    config: NavConfig,
    rec: Recording,
    layout: Layout,
    exclude: Array | None = None,
) -> tuple[Array, Array]:
    """Fuse the forward pass with a filter run over the time-reversed data (seed 001 RTS-FC).

    The backward filter starts at the receive trap with the forward estimate's azimuth there as
    its initial heading (with the configured sigma: a prior, not the forward's information)
    and leaves out the same odometer epochs; its heading prior stays outside it until its
    second marker (:class:`~pipe_nav_core.anchoring.FreeHeading`) and is added to its covariance
    here. Returns the corrections to the forward estimates
    and the variances (K, n) of the fused covariances.
    """
    t_f = rec.t
    _, _, az_end = att.euler_from_dcm(NavState.from_vector(rec.states[-1]).c_nb)
    cfg_b = replace(config, heading_source="fixed", initial_azimuth=float(az_end))
    ex_b = None if exclude is None else -np.asarray(exclude)[::-1, ::-1]
    back = run_forward(
        reverse_log(log),
        cfg_b,
        reverse=True,
        epoch_times=-t_f[::-1],
        odometer_exclude=ex_b,
        free_heading=True,
    )
    rb = back.recording
    assert rb is not None
    # the backward epoch j at the time of forward epoch k (to the microsecond; the backward
    # epochs run backwards in time), where there is one other than its alignment
    key_b = np.round(-rb.t * 1e6)[::-1]
    key_f = np.round(t_f * 1e6)
    i = np.minimum(np.searchsorted(key_b, key_f), len(key_b) - 1)
    j = len(key_b) - 1 - i
    ks = np.flatnonzero((key_b[i] == key_f) & (j > 0))
    js = j[ks]
    # the backward estimate after its updates, in forward terms (velocity and gyro bias
    # negate): at the time of forward epoch k it holds the measurements after t_k (the backward
    # epoch ending there applies those of the block (t_k, t_k+1]), the forward filter those up
    # to t_k. Its prediction instead lost one block: at a marker, the marker itself (the fused
    # centreline was 0.86 m off for one epoch before each marker on field10k_sparse)
    xb = rb.states[js].copy()
    xb[:, SV_VEL] *= -1.0
    xb[:, SV_BG] *= -1.0
    d = difference_many(xb, rec.states[ks], layout)
    flip = _flip(layout)
    free = back.free_heading
    if free is not None:  # its heading prior, kept outside until its second marker
        on = rb.t[js] < free.until
        g = free.direction(xb[:, SV_LAT], xb[:, SV_LON], xb[:, SV_H], xb[:, SV_VEL], layout)
        g *= np.sqrt(free.variance) * on[:, None]
    e = np.zeros((len(t_f), layout.n))
    var = rec.variances()
    for b in range(0, len(ks), FUSE_BATCH):
        sel = slice(b, b + FUSE_BATCH)
        P_f = rec.covariances(ks[sel], "upd")
        P_b = rb.covariances(js[sel], "upd") * np.outer(flip, flip)
        if free is not None:
            P_b += g[sel, :, None] * g[sel, None, :]
        d_b = d[sel]
        if layout.odoq is not None:
            # its reading error at the start of a reversed epoch is a later reading's: unknown
            q = layout.odoq.start
            P_b[:, q, :] = 0.0
            P_b[:, :, q] = 0.0
            P_b[:, q, q] = 1.0
            d_b[:, q] = 0.0
        # inverse-covariance weighting (smoothing.fuse_covariance) of every epoch at once
        gain = np.linalg.solve(P_f + P_b, P_f).transpose(0, 2, 1)
        e[ks[sel]] = (gain @ d_b[:, :, None])[:, :, 0]
        var[ks[sel]] = np.diagonal(P_f - gain @ P_f, axis1=1, axis2=2)
    rb.close()
    return e, var


SAMPLE_BATCH = 1 << 18  # samples corrected at once by _centreline (bounds its temporaries)


def _centreline(rec: Recording, e: Array, var: Array, layout: Layout) -> Trajectory:
    """Apply the smoothed corrections to the per-sample nominal trajectory.

    e (K, n): smoothed corrections to the filter's estimates, var (K, n) their variances; the
    correction relative to the linearization point of epoch k is x_upd[k] + e[k]; a block's
    nominal starts on lin[k - 1] and ends end_offset[k] short of lin[k]; in between the
    correction is interpolated in time.
    """
    cols = np.r_[layout.pos, layout.att]  # the corrections the centreline needs
    P, A = slice(0, 3), slice(3, 6)
    d_lin = rec.x_upd[:, cols] + e[:, cols]
    d_end = d_lin + rec.end_offset[:, cols]
    var_c = var[:, cols]
    t_ep = rec.t
    t = rec.s_t.copy()
    N = len(t)
    lat, lon, h = np.empty(N), np.empty(N), np.empty(N)
    q = np.empty((N, 4))
    sig_p, sig_a = np.empty((N, 3)), np.empty((N, 3))
    for b in range(0, N, SAMPLE_BATCH):
        s = slice(b, b + SAMPLE_BATCH)
        k = rec.s_epoch[s]
        frac = (t[s] - t_ep[k - 1]) / np.maximum(t_ep[k] - t_ep[k - 1], 1e-12)
        w0, w1 = (1.0 - frac)[:, None], frac[:, None]
        corr = w0 * d_lin[k - 1] + w1 * d_end[k]
        dlat, dlon, dh = earth.enu_to_geodetic_increment(corr[:, P], rec.s_lat[s], rec.s_h[s])
        lat[s], lon[s], h[s] = rec.s_lat[s] + dlat, rec.s_lon[s] + dlon, rec.s_h[s] + dh
        q[s] = att.quat_normalize(att.quat_mul(att.quat_from_rotvec(corr[:, A]), rec.s_q[s]))
        var_s = w0 * var_c[k - 1] + w1 * var_c[k]
        sig_p[s] = np.sqrt(np.maximum(var_s[:, P], 0.0))
        sig_a[s] = np.sqrt(np.maximum(var_s[:, A], 0.0))
    distance = arc_chainage(lat, lon, h, q)
    enu = earth.geodetic_to_enu(lat, lon, h, lat[0], lon[0], h[0])
    vel = np.gradient(enu, t, axis=0) if N > 1 else np.zeros((N, 3))
    return Trajectory(t, lat, lon, h, vel, q, distance, sig_p, sig_a)


def arc_chainage(lat: Array, lon: Array, h: Array, quat_nb: Array) -> Array:
    """Chainage (m, 0 at the first sample) as the smoothed path's length, signed along the
    body axis (backing up counts down): a slipping, stuck or spiking wheel does not corrupt
    it. Steps in the local ENU of each sample (lat, lon rad, h m; quat_nb base_link->ENU)."""
    if len(lat) < 2:
        return np.zeros(len(lat))
    rm, rn = earth.radii(lat[1:])
    step = np.stack([np.diff(np.unwrap(lon)) * (rn + h[1:]) * np.cos(lat[1:]),
                     np.diff(lat) * (rm + h[1:]), np.diff(h)], axis=1)  # fmt: skip
    axis = att.dcm_from_quat(quat_nb[1:])[:, :, 0]
    return np.r_[0.0, np.cumsum(np.einsum("ij,ij->i", step, axis))]


def _forward_trajectory(rec: Recording) -> Trajectory:
    """The forward filter's estimates, one per epoch (copies: the recording may go)."""
    st = rec.states
    var = rec.variances()
    lay = rec.layout
    return Trajectory(
        t=st[:, SV_T].copy(),
        lat=st[:, SV_LAT].copy(),
        lon=st[:, SV_LON].copy(),
        h=st[:, SV_H].copy(),
        vel_n=st[:, SV_VEL].copy(),
        quat_nb=st[:, SV_Q].copy(),
        distance=st[:, SV_DIST].copy(),
        sigma_enu=np.sqrt(var[:, lay.pos]),
        sigma_att=np.sqrt(var[:, lay.att]),
    )


def _with_free_heading(traj: Trajectory, free: FreeHeading | None) -> Trajectory:
    """traj with the uncertainty of the heading the filter left unanchored (FreeHeading)
    added to its horizontal position and azimuth sigmas (in place; returned)."""
    if free is None or traj.sigma_enu is None or traj.sigma_att is None:
        return traj
    extra = free.variances(traj.t, traj.lat, traj.lon, traj.h)
    traj.sigma_enu[:, :2] = np.sqrt(traj.sigma_enu[:, :2] ** 2 + extra[:, :2])
    traj.sigma_att[:, 2] = np.sqrt(traj.sigma_att[:, 2] ** 2 + extra[:, 2])
    return traj


def interpolate_enu(traj: Trajectory, times: Array, datum: Datum) -> Array:
    """ENU positions (m) of a trajectory at the given times (linear interpolation)."""
    enu = earth.geodetic_to_enu(traj.lat, traj.lon, traj.h, datum.lat, datum.lon, datum.alt)
    return np.stack([np.interp(times, traj.t, enu[:, i]) for i in range(3)], axis=-1)


def marker_residuals(traj: Trajectory, markers: list[Marker]) -> dict[str, Array]:
    """name -> estimate minus survey, ENU m, at each marker passage inside the trajectory."""
    out: dict[str, Array] = {}
    if not len(traj):
        return out
    for m in markers:
        if traj.t[0] <= m.t <= traj.t[-1]:
            i = int(np.searchsorted(traj.t, m.t))
            s = slice(max(i - 1, 0), i + 1)  # the samples around the passage
            enu = earth.geodetic_to_enu(traj.lat[s], traj.lon[s], traj.h[s], m.lat, m.lon, m.alt)
            out[m.name] = np.array([np.interp(m.t, traj.t[s], enu[:, c]) for c in range(3)])
    return out


def summarize(result: SmoothResult, nav: Navigator) -> dict[str, object]:
    """Figures for people: distance, duration, markers, rejected updates, calibration."""
    c = result.centreline
    diag = nav.diagnostics()
    s = nav.state
    inside = (
        (c.t >= result.markers[0].t) & (c.t <= result.markers[-1].t)
        if result.markers
        else np.ones(len(c), bool)
    )
    sig_h = (
        np.hypot(c.sigma_enu[:, 0], c.sigma_enu[:, 1])
        if c.sigma_enu is not None
        else np.zeros(len(c))
    )
    out: dict[str, object] = {
        "distance_m": float(c.distance[-1]) if len(c) else 0.0,
        "duration_s": float(c.t[-1] - c.t[0]) if len(c) else 0.0,
        "markers_total": len(result.markers),
        "markers_used": int(diag.get("accepted_marker", 0)),
        "markers_rejected": int(diag.get("rejected_marker", 0)),
        "rejected_updates": {k[9:]: v for k, v in diag.items() if k.startswith("rejected_") and v},
        "odometer_scale": float(1.0 + s.k) if s else 1.0,
        "gyro_bias_deg_h": [float(x) for x in np.degrees(s.bg) * 3600] if s else [],
        "accel_bias_mg": [float(x) for x in s.ba / 9.80665 * 1e3] if s else [],
        "max_sigma_h_between_markers_m": float(sig_h[inside].max()) if inside.any() else 0.0,
        "max_marker_residual_m": float(
            max((np.linalg.norm(v) for v in result.marker_residuals.values()), default=0.0)
        ),
        "warnings": nav.model_warnings(),
    }
    return out
