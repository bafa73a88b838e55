"""The two-filter smoother (seed 001 RTS-FC, seed 004): the forward filter's estimates fused, by
inverse-covariance weighting (:func:`fuse`), with those of the same engine run in covariance
form over the time-reversed data (:func:`two_filter`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.app.progress import QUIET, Progress
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.navigator import Navigator
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.model.state import (
    SV_BG,
    SV_DIST,
    SV_H,
    SV_LAT,
    SV_LON,
    SV_VEL,
    Layout,
    NavState,
    difference_many,
)
from pipe_nav_core.smooth.forward import run_forward
from pipe_nav_core.smooth.logs import reverse_log
from pipe_nav_core.smooth.recording import Recording
from pipe_nav_core.types import SensorLog

Array = NDArray[np.float64]
FUSE_BATCH = 1024  # epochs fused at once (bounds the (B, n, n) temporaries)


def fuse(P_f: Array, P_b: Array, d: Array, cols: Array | None = None) -> tuple[Array, Array]:
    """Inverse-covariance weighting (seed 001 eq. 29-30) of B pairs of independent estimates
    of the same error state: forward covariances P_f (B, n, n) (symmetric), backward ones P_b
    (B, n, n), d (B, n) the backward estimate minus the forward one. Returns the corrections to
    the forward estimates K d (B, n) and the variances (B, len(cols)) of the fused covariances
    P_f - K P_f at the states ``cols`` (every state when None), where K = P_f (P_f + P_b)^-1.
    One solve with the columns asked for: K d = P_f y with (P_f + P_b) y = d, and the fused
    variance of state c is P_f[c, c] - P_f[:, c] . z_c with (P_f + P_b) z_c = P_f[:, c]."""
    cols = np.arange(P_f.shape[1]) if cols is None else np.asarray(cols)
    rhs = np.concatenate([d[:, :, None], P_f[:, :, cols]], axis=2)
    y = np.linalg.solve(P_f + P_b, rhs)
    e = (P_f @ y[:, :, :1])[:, :, 0]
    return e, P_f[:, cols, cols] - np.einsum("bic,bic->bc", P_f[:, :, cols], y[:, :, 1:])


def two_filter(
    log: SensorLog,
    config: NavConfig,
    rec: Recording,
    layout: Layout,
    exclude: Array | None = None,
    progress: Progress = QUIET,
    cols: Array | None = None,
    straight: tuple[Array, Array] | None = None,
) -> tuple[Array, Array]:
    """Fuse the forward pass recorded in ``rec`` with a filter run over the time-reversed log
    (:func:`backward_pass` at rec's epochs from the forward estimate's azimuth at the end, then
    :func:`fuse_passes`). Returns the corrections (K, n) to the forward estimates and the
    variances (K, len(cols)) of the fused covariances at the states ``cols`` (every state when
    None); ``progress`` hears the backward pass. ``straight``: the forward pass's straight
    sections (plan, vertical; chainage intervals, m), which the backward filter takes too."""
    back = backward_pass(log, config, rec.t, end_azimuth(rec.states[-1]), exclude, progress,
                         backward_sections(straight, float(rec.states[-1][SV_DIST])))  # fmt: skip
    return fuse_passes(rec, back, layout, cols)


def end_azimuth(state: Array) -> float:
    """The azimuth (rad, from north, clockwise) of a flat state (SV_SIZE,): the backward
    filter's initial heading."""
    _, _, az = att.euler_from_dcm(NavState.from_vector(state).c_nb)
    return float(az)


def backward_sections(
    straight: tuple[Array, Array] | None, end: float
) -> tuple[Array, Array] | None:
    """The forward pass's straight sections (plan, vertical: chainage intervals (K, 2), m;
    :func:`.straight_pipe.sections`) in the backward filter's chainage, which is zero at the
    receive trap (the forward chainage ``end``, m) and falls towards the launch; None
    without them."""
    if straight is None:
        return None
    return straight[0] - end, straight[1] - end


def backward_pass(
    log: SensorLog,
    config: NavConfig,
    t_f: Array,
    azimuth: float,
    exclude: Array | None = None,
    progress: Progress = QUIET,
    straight: tuple[Array, Array] | None = None,
) -> Navigator:
    """The backward filter: the forward engine run over the time-reversed log, with its epochs
    at the forward epochs' times ``t_f`` (s), from the receive trap with ``azimuth`` (rad) as
    its initial heading (with the configured sigma: a prior, not the forward's information),
    leaving out the same odometer epochs (``exclude``, (N, 2) s); its heading prior stays
    outside it until its second marker (:class:`~pipe_nav_core.filter.anchoring.FreeHeading`).
    It needs no more of the forward pass than those epochs and that heading (and the straight
    sections ``straight`` of its reference, in the backward chainage: :func:`backward_sections`),
    so it can run beside it (the GIL is let go in the compiled epochs)."""
    cfg_b = replace(config, heading_source="fixed", initial_azimuth=azimuth)
    ex_b = None if exclude is None else -np.asarray(exclude)[::-1, ::-1]
    return run_forward(
        reverse_log(log),
        cfg_b,
        reverse=True,
        epoch_times=-np.asarray(t_f)[::-1],
        odometer_exclude=ex_b,
        free_heading=True,
        straight=straight,
        progress=progress,
    )


def fuse_passes(
    rec: Recording, back: Navigator, layout: Layout, cols: Array | None = None
) -> tuple[Array, Array]:
    """Fuse the forward pass recorded in ``rec`` with the backward filter ``back``
    (:func:`backward_pass`), epoch by epoch where both have one: the corrections (K, n) to the
    forward estimates and the variances (K, len(cols)) of the fused covariances at the states
    ``cols`` (every state when None; elsewhere the forward ones). The backward filter's
    heading prior, kept outside it until its second marker, is added to its covariance here;
    its recording is closed."""
    t_f = rec.t
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
    # to t_k, so that no measurement is in both or in neither (the backward prediction would
    # lack the block (t_k, t_k+1], at a marker the marker itself)
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
    # what the backward filter does not know: its odometer reading error at the start of a
    # reversed epoch (a later reading's), and the section direction (both filters restart it
    # at a section's start, at opposite ends: between sections they hold different ones)
    unknown = [] if layout.odoq is None else [layout.odoq.start]
    if layout.dir is not None:
        unknown += list(range(layout.dir.start, layout.dir.stop))
    e = np.zeros((len(t_f), layout.n))
    var = rec.variances() if cols is None else rec.variances()[:, cols]
    for b in range(0, len(ks), FUSE_BATCH):
        sel = slice(b, b + FUSE_BATCH)
        P_f = rec.covariances(ks[sel], "upd")
        P_b = rb.covariances(js[sel], "upd") * np.outer(flip, flip)
        if free is not None:
            P_b += g[sel, :, None] * g[sel, None, :]
        d_b = d[sel]
        for q in unknown:
            P_b[:, q, :] = 0.0
            P_b[:, :, q] = 0.0
            P_b[:, q, q] = 1.0
            d_b[:, q] = 0.0
        e[ks[sel]], var[ks[sel]] = fuse(P_f, P_b, d_b, cols)
    rb.close()
    return e, var


def _flip(layout: Layout) -> Array:
    """Signs mapping reversed-time error states to forward ones (velocity, gyro bias negate)."""
    s = np.ones(layout.n)
    if layout.vel is not None:
        s[layout.vel] = -1.0
    s[layout.bg] = -1.0
    return s
