"""Straight pipe between bends: where the previous pass's smoothed path runs straight, the pig's
path does not turn, so the body turns neither about the pipe's horizontal normal nor about
the normal in its vertical plane. Between markers this is the information that binds the
gyro's bias and error matrix while the pig moves, as the zero-rate update does at stops; with
a consumer-grade gyro and markers only at the pipe's ends it halves the horizontal error
(BENCHMARKS.md, "The straight-pipe update").

The two rows (rad/s) are the body's rate relative to the ground, omega_nb = (I + E)^-1
(gyro_mean - b_g) - C_nb^T w_ie (base_link; E the gyro error matrix where the layout has it),
about two axes across the bore (base_link x): the one that turns the pipe's axis t in plan,
u = t x n, and the one that turns it in its vertical plane, n = (up x t) / |up x t| (both in
ENU at the linearization point, held in base_link). Rolling about the axis turns neither.
Each row applies where the path is straight in its plane: the chainage intervals
:func:`sections` finds in the pass's reference trajectory (so only passes linearized about
a reference have the update), leaving out ``straight_pipe_margin`` at each end of a bend. Its
noise is the gyro's angle random walk over the epoch with ``straight_pipe_sigma`` added: the
pig's wobble and the pipe's own waviness (1e-3 rad/s by default: a curvature of 1e-3 1/m at
1 m/s; 0 turns the update off).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.jit import kernel
from pipe_nav_core.model.measurements.context import Context, factor, update
from pipe_nav_core.model.state import (
    I_BG,
    I_BORE,
    I_GM,
    I_Q,
    L_ATT,
    L_BG,
    L_BORE,
    L_GM,
    L_N,
    SV_DIST,
    SV_LAT,
    SV_T,
    c_nb_k,
    odometer_axis,
)

if TYPE_CHECKING:
    from pipe_nav_core.config import NavConfig
    from pipe_nav_core.model.measurements.context import Array, Factor, Index, Model, Tally

KINDS, EVENTS = ("straight",), ()  # its update (statistics), the events it counts
NO_SECTIONS = np.zeros((0, 2))  # (K, 2) chainage intervals: none
WINDOW_M = 2.0  # m of path over which sections() measures the curvature
GRID_M = 0.25  # m: the chainage step sections() measures at
OTHER_CURVATURE = 0.02  # 1/m: the other plane's curvature up to which a plane's row applies
SCALES_M = 4.0 * 2.0 ** np.arange(9)  # m: the windows a gentle curve is looked for over (4-1024)
N_SIGMA = 3.0  # sigmas of the reference's own noise a curve turns by beyond N_WANDER ...
N_WANDER = 2.5  # ... sigmas of the section's wander (what the rows allow it)
GROW = 3.0  # times the length over which a stretch's curvature shows that it grows by
END_SCALE_M = 16.0  # m: the windows in which a section's end stands for the half it cuts off


@kernel
def axes_k(sv: Array) -> Array:
    """(2, 3) the base_link directions across the bore about which a rate turns the pipe's
    axis in plan (row 0: u = t x n in ENU) and in its vertical plane (row 1: n = up x t,
    horizontal), t the direction of travel in ENU (:func:`~pipe_nav_core.model.state.travel_axis_k`:
    a pig rolls about it); zeros where the axis is vertical."""
    c = c_nb_k(sv)
    u, _ = odometer_axis(sv[I_BORE : I_BORE + 2])
    t = c @ u  # travel_axis_k's, with the C_nb this function needs anyway
    te, tn, tu = t[0], t[1], t[2]
    h = np.hypot(te, tn)
    enu = np.zeros((2, 3))
    if h > 1e-6:
        enu[0, 0], enu[0, 1], enu[0, 2] = -tu * te / h, -tu * tn / h, h
        enu[1, 0], enu[1, 1] = -tn / h, te / h
    return enu @ c


@kernel
def straight_pipe_k(
    sv: Array,
    L: Index,
    gyro_mean: Array,
    gyro_slow: Array,
    sigma: float,
    earth_sign: float,
    axes: Array,
) -> Model:
    """The components along ``axes`` (m, 3; base_link, across the bore) of the body's rate
    relative to the ground, omega_nb (rad/s), less its roll about the direction of travel
    u(boresight) (a pig rolls about the pipe's axis): zero on a straight pipe. Residual, H and
    R (sigma rad/s on each row). The axes are inputs (the policy's, from the linearization
    point: :func:`axes_k`), so that both planes' rows turn with the body as the bore does; the
    roll taken out about u(boresight) is the state's, so that the roll shows the boresight.

    The gyro error matrix's columns multiply the corrected rate, and they take it from
    ``gyro_slow`` (rad/s, base_link; the readings of the epochs before, low-passed), not from
    ``gyro_mean``. The residual holds the epoch's gyro noise, and a column holding the same
    noise correlates with it, so the update would read the noise as a scale factor (errors in
    variables). A consumer gyro's noise over an epoch is as large as the rates the rows see:
    it biased the yaw gyro's scale factor 0.5-3 % high on the undulating pipe (BENCHMARKS.md,
    "The straight-pipe rows' scale-factor columns"). With gyro_slow equal to gyro_mean, H is
    the residual's exact Jacobian."""
    c = c_nb_k(sv)
    w_ie = earth.earth_rate_k(sv[SV_LAT], earth_sign)
    u, du = odometer_axis(sv[I_BORE : I_BORE + 2])
    gm = L[L_GM]
    inv = np.eye(3)
    if gm >= 0:
        inv = att.inv3(np.eye(3) + sv[I_GM : I_GM + 9].copy().reshape(3, 3))
    w_ib = inv @ (gyro_mean - sv[I_BG : I_BG + 3])
    w_nb = w_ib - c.T @ w_ie
    roll = u @ w_nb
    across = axes @ (np.eye(3) - np.outer(u, u))  # d(rows)/d(omega_nb)
    mi = across @ inv  # d(rows)/d(raw rate)
    m = axes.shape[0]
    H = np.zeros((m, L[L_N]))
    H[:, L[L_BG] : L[L_BG] + 3] = -mi
    if gm >= 0:
        w_col = inv @ (gyro_slow - sv[I_BG : I_BG + 3])
        for r in range(3):
            for j in range(3):
                H[:, gm + 3 * r + j] = -mi[:, r] * w_col[j]
    a = L[L_ATT]
    H[:, a : a + 3] = -(across @ c.T @ att.skew_k(w_ie))
    b = L[L_BORE]
    if b >= 0:
        du_w = w_nb @ du  # (2,): the roll's change with the boresight
        for j in range(2):
            H[:, b + j] = -(axes @ (du[:, j] * roll + u * du_w[j]))
    return -(axes @ (w_nb - u * roll)), H, np.eye(m) * sigma**2


@kernel
def section_of(sections: Array, d: float) -> int:
    """The interval of the sorted, disjoint intervals (K, 2) that chainage d (m) is inside,
    -1 if none."""
    i = np.searchsorted(sections[:, 0], d, side="right") - 1
    return i if i >= 0 and d <= sections[i, 1] else -1


@kernel
def inputs_k(c: Context) -> tuple[bool, tuple[Array, Array, float, float, Array]]:
    """Whether the epoch has the update (moving, on a straight section in plan or in its
    vertical plane) and straight_pipe_k's inputs after sv, L (the rows of the planes it is
    straight in)."""
    prm = c.prm
    lo, hi = 0, 0
    if prm.straight_sigma > 0.0 and not c.stopped and c.T > 0.0:
        d = c.s[SV_DIST]
        flat, level = section_of(prm.straight_h, d) >= 0, section_of(prm.straight_v, d) >= 0
        lo, hi = (0 if flat else 1), (2 if level else 1)
    if hi == lo:  # the axes only where a row may apply: the live filter's epochs have none
        return False, (c.gyro_mean, c.gyro_slow, 0.0, prm.earth_sign, np.zeros((0, 3)))
    axes = axes_k(c.s)
    if axes[1, 0] == 0.0 and axes[1, 1] == 0.0:
        hi = lo  # a vertical axis: neither plane is defined
    sigma = np.sqrt(prm.imu[0] ** 2 / c.T + prm.straight_sigma**2)
    return hi > lo, (c.gyro_mean, c.gyro_slow, sigma, prm.earth_sign, axes[lo:hi].copy())


@kernel
def apply(c: Context, x: Array, P: Array, tally: Tally, kind: int, event: int) -> None:
    """The update where :func:`inputs_k` says so, counted under kind."""
    on, args = inputs_k(c)
    if on:
        r, H, R = straight_pipe_k(c.s, c.L, *args)
        update(kind, r, H, R, x, P, c.prm.chi2, tally)


def factors(c: Context) -> list[Factor]:
    """The update :func:`apply` makes at this context, as a model of the state."""
    on, args = inputs_k(c)
    return [factor(KINDS[0], straight_pipe_k, *args)] if on else []


class Sections(NamedTuple):
    """Where a path runs straight: chainage intervals (K, 2; m, sorted, disjoint) in plan and
    in its vertical plane, and the gentle curves found (plan, vertical; (K, 2), m)."""

    plan: Array
    vertical: Array
    curves: tuple[Array, Array]


def sections(
    reference: Array,
    config: NavConfig,
    gyro_arw: float | None = None,
    curves: tuple[Array, Array] | None = None,
) -> Sections:
    """Where the path of flat states ``reference`` (K, SV_SIZE; a pass's smoothed trajectory)
    runs straight in plan and in its vertical plane, by ``config``'s straight_pipe_curvature,
    _margin and _wander and the gyro's angle random walk (rad/sqrt(s); None: config's IMU
    model's). ``curves``: the gentle curves an earlier pass found, left out as well (a pass
    that held a curve's ends straight flattens them, so the next pass would find less of it).
    Epochs whose chainage, time or attitude is not finite (a pass that diverged) are left out.

    Two tests, both of which a section passes:
    - a bend: the axis (base_link x) turns by more than straight_pipe_curvature (1/m) over
      WINDOW_M of chainage; straight_pipe_margin (m) is left out at each of its ends;
    - a gentle curve (a radius of a kilometre turns a milliradian in a metre, below what
      WINDOW_M sees through the gyro's noise, but 35 mrad in 50 m): over every window of
      SCALES_M about a point (clipped to the section the first test leaves), the axis turns on
      both sides of it (one near the section's end) by more than N_WANDER sigmas of the
      section's wander (straight_pipe_wander per sqrt(m)) and N_SIGMA of the reference's own
      angle random walk (gyro ARW per sqrt(s)) allow (:func:`_curved`); the same margin is
      left out about such points. Else the rows would hold such a curve straight: on a 90 m
      pipe with a 2 deg curve of 1500 m radius, 48 cm of error at 14 sigma (BENCHMARKS.md,
      "Gentle curves"). A curve gentler than the gyro's bias can show (a consumer gyro's
      1.2e-4 rad/s at 0.6 m/s: a radius of 5 km) is not found."""
    ok = np.isfinite(reference[:, SV_DIST]) & np.isfinite(reference[:, I_Q : I_Q + 4]).all(1)
    ok &= np.isfinite(reference[:, SV_T])
    ref = reference[ok]
    order = np.argsort(ref[:, SV_DIST], kind="stable")
    d = ref[order, SV_DIST]
    earlier = curves if curves is not None else (NO_SECTIONS, NO_SECTIONS)
    none = Sections(NO_SECTIONS, NO_SECTIONS, earlier)
    if len(d) < 2:
        return none
    keep = order[np.r_[True, np.diff(d) > 1e-6]]  # the first epoch at each chainage (stops)
    d = ref[keep, SV_DIST]
    if len(d) < 2 or d[-1] - d[0] < WINDOW_M:
        return none
    t = ref[keep, SV_T]
    _, pitch, azimuth = att.euler_from_dcm(att.dcm_from_quat(ref[keep, I_Q : I_Q + 4]))
    azimuth = np.unwrap(azimuth)
    # GRID_M, or coarser where the epochs are further apart (a diverged pass's chainage)
    step = max(GRID_M, (d[-1] - d[0]) / (4 * len(d)))
    grid = np.arange(d[0], d[-1] + step, step)
    half = WINDOW_M / 2
    lo, hi = np.clip(grid - half, d[0], d[-1]), np.clip(grid + half, d[0], d[-1])
    span = np.maximum(hi - lo, step)
    ends = (float(d[0]), float(d[-1]))
    cos_pitch = np.cos(np.interp(grid, d, pitch))

    def turn(angle: Array) -> Array:
        return np.abs(np.interp(hi, d, angle) - np.interp(lo, d, angle)) / span

    plan = turn(azimuth) * cos_pitch
    vertical = turn(pitch)
    # a plane's row is left out where the other plane turns faster than OTHER_CURVATURE too:
    # there a milliradian of axis or gyro misalignment leaks the other plane's turn into it
    reach = config.straight_pipe_margin + half
    kappa = config.straight_pipe_curvature
    wander = config.straight_pipe_wander
    arw = config.imu_spec().gyro_arw if gyro_arw is None else gyro_arw
    out, found = [], []
    for flat, angle, scale, known in (
        ((plan <= kappa) & (vertical <= OTHER_CURVATURE), azimuth, cos_pitch, earlier[0]),
        ((vertical <= kappa) & (plan <= OTHER_CURVATURE), pitch, 1.0, earlier[1]),
    ):
        candidates = _straight(grid, flat, reach, *ends)
        curved = _curved(grid, candidates, d, t, angle, scale, wander, arw)
        curved |= _within(known, grid)
        out.append(_straight(grid, flat & ~curved, reach, *ends))
        found.append(_runs(grid, curved))
    return Sections(out[0], out[1], (found[0], found[1]))


def _within(intervals: Array, d: Array) -> Array:
    """Whether each chainage of d (m) lies inside one of ``intervals`` (K, 2; sorted, disjoint):
    :func:`section_of` >= 0 for all of them at once."""
    if len(intervals) == 0:
        return np.zeros(len(d), dtype=bool)
    i = np.searchsorted(intervals[:, 0], d, side="right") - 1
    return (i >= 0) & (d <= intervals[np.maximum(i, 0), 1])


def _runs(grid: Array, flags: Array) -> Array:
    """The intervals (K, 2; m) from the first to the last grid point of each run of flags."""
    edges = np.flatnonzero(np.diff(np.r_[0, flags.astype(np.int8), 0]))
    return np.ascontiguousarray(np.c_[grid[edges[::2]], grid[edges[1::2] - 1]]).reshape(-1, 2)


def _curved(
    grid: Array,
    candidates: Array,
    d: Array,
    t: Array,
    angle: Array,
    scale: Array | float,
    wander: float,
    arw: float,
) -> Array:
    """Which grid points (m of chainage) of the intervals ``candidates`` (K, 2; m) lie inside
    a curve: over both halves of a window of SCALES_M about the point (clipped to its
    interval), ``angle`` (rad, at chainages d and times t; times ``scale``) turns by more than
    sqrt((N_WANDER wander)^2 L + (N_SIGMA arw)^2 T): what the section may wander over the
    half's length L (m), and the reference's own noise over its duration T (s).
    Both halves, so that a window reaching into a curve from the straight pipe beside it does
    not take that pipe for the curve; but in windows up to END_SCALE_M a half cut short by the
    interval's end (a bend's margin, the run's end) is not asked, so that a curve running into
    the end is found up to it (and straight pipe within END_SCALE_M / 2 of the end may be
    taken with it)."""
    curved = np.zeros(len(grid), dtype=bool)
    for a, b in candidates:
        inside = slice(np.searchsorted(grid, a, "left"), np.searchsorted(grid, b, "right"))
        g = grid[inside]
        s = scale[inside] if isinstance(scale, np.ndarray) else scale
        at_g, t_g = np.interp(g, d, angle), np.interp(g, d, t)
        hit = np.zeros(len(g), dtype=bool)
        for w in SCALES_M:
            if w > 2 * (b - a):
                break
            both, either = np.ones(len(g), dtype=bool), np.zeros(len(g), dtype=bool)
            for end in (np.maximum(g - w / 2, a), np.minimum(g + w / 2, b)):
                length = np.abs(end - g)
                turned = (np.interp(end, d, angle) - at_g) * s
                duration = np.abs(np.interp(end, d, t) - t_g)
                allowed = (N_WANDER * wander) ** 2 * length + (N_SIGMA * arw) ** 2 * duration
                bent = turned**2 > allowed
                both &= bent | ((length < w / 2 - 1e-9) & (w <= END_SCALE_M))
                either |= bent
            hit |= both & either
        # a curve's ends turn too little for a window to see (within the first metres): each
        # found stretch grows by the length over which its own curvature would be seen, at
        # most its own length (a stretch that barely turns is not taken for a long curve)
        for c0, c1 in _runs(g, hit):
            if c1 <= c0:
                continue
            kappa = abs(np.interp(c1, d, angle) - np.interp(c0, d, angle)) / (c1 - c0)
            pace = (np.interp(c1, d, t) - np.interp(c0, d, t)) / (c1 - c0)  # s/m
            per_m = (N_WANDER * wander) ** 2 + (N_SIGMA * arw) ** 2 * pace
            grow = min(GROW * per_m / max(kappa, 1e-12) ** 2, c1 - c0, END_SCALE_M / 2)
            hit |= (g >= c0 - grow) & (g <= c1 + grow)
        curved[inside] = hit
    return curved


def _straight(grid: Array, flat: Array, margin: float, start: float, end: float) -> Array:
    """The intervals (K, 2) of [start, end] (m) further than margin from every grid point that
    is not flat."""
    bent = grid[~flat]
    if len(bent) == 0:
        return np.array([[start, end]])
    edges = np.r_[start, np.c_[bent - margin, bent + margin].ravel(), end].reshape(-1, 2)
    # between consecutive bent points' reaches (they may overlap: then no interval)
    out = edges[edges[:, 1] - edges[:, 0] > 0]
    return np.ascontiguousarray(out, dtype=np.float64).reshape(-1, 2)
