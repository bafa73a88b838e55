"""The PNG report plot of a centreline (headless: matplotlib's Agg canvas, no pyplot state).

Four panels: plan view (east/north in ``map``, equal aspect, markers labelled), elevation
profile along the chainage with the +-3 sigma band of ``up``, the one-sigma horizontal and
vertical position uncertainty along the chainage, and the residual (estimate minus survey, ENU
components) at each marker with the estimate's 3-sigma error bars. With the run's integrity
products (``integrity``) a fifth, full-width panel below them: the bending strain along the
chainage (log scale, percent; curvature on the right axis) with its one-sigma band, the strain
thresholds as horizontal lines, the strain features as bars on their threshold, and the bends
marked and numbered at their apex.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.io.atomic import atomic_write
from pipe_nav_core.io.centreline import interpolate_trajectory
from pipe_nav_core.types import Datum, Marker, Trajectory

if TYPE_CHECKING:
    from pipe_nav_core.products.integrity import IntegrityReport

_MAX_POINTS = 3000  # per line: a panel is about 700 pixels wide
_COLORS = {"e": "tab:blue", "n": "tab:orange", "u": "tab:green"}
_MAX_BEND_LABELS = 60  # bends numbered in the strain panel (every k-th beyond that)
_TICKS_AHEAD = 10  # ticks per axis made with a prepared figure (prepare_figure)
_STRAIN_FLOOR = 1.0 / 25.0  # strain panel bottom, as a fraction of the lowest threshold


# the titles' height, fixed: matplotlib then skips placing them above the axes' top tick labels
# (there are none), a third of drawing the report
TITLE_Y = 1.0


def _decimate(n: int) -> NDArray[np.int64]:
    if n <= _MAX_POINTS:
        return np.arange(n)
    idx = np.linspace(0, n - 1, _MAX_POINTS).round().astype(np.int64)
    return np.unique(idx)


def _envelope(y: NDArray[np.float64]) -> NDArray[np.int64]:
    """Indices of at most _MAX_POINTS samples keeping each bin's minimum and maximum (a thin
    peak survives decimation, unlike with evenly spaced samples)."""
    n = len(y)
    if n <= _MAX_POINTS:
        return np.arange(n)
    bins = _MAX_POINTS // 2
    edges = np.linspace(0, n, bins + 1).round().astype(np.int64)
    width = int(np.diff(edges).max())
    start = np.repeat(edges[:-1], np.diff(edges))
    slot = np.arange(n) - start + np.repeat(np.arange(bins) * width, np.diff(edges))
    grid = np.full(bins * width, np.nan)
    grid[slot] = y
    grid = grid.reshape(bins, width)
    finite = np.isfinite(grid)
    hi = np.where(finite, grid, -np.inf).argmax(axis=1)
    lo = np.where(finite, grid, np.inf).argmin(axis=1)
    idx = np.concatenate([edges[:-1] + hi, edges[:-1] + lo])
    return np.unique(np.clip(idx, 0, n - 1))


def _plain_number(value: float, _position: object = None) -> str:
    """A log axis's tick label as a plain number (0.01, 0.1, 1, 10)."""
    return f"{value:g}"


def _strain_panel(ax: Any, integrity: IntegrityReport, dscale: float, dunit: str) -> None:
    """The strain-along-chainage panel (see the module docstring)."""
    from matplotlib.ticker import FuncFormatter, NullLocator

    prof = integrity.profile
    d = np.asarray(prof.distance, dtype=np.float64)
    strain = np.asarray(integrity.strain_pct, dtype=np.float64).reshape(len(d))
    sigma = np.asarray(integrity.sigma_strain_pct, dtype=np.float64).reshape(len(d))
    thresholds = sorted(float(x) for x in integrity.thresholds_pct if x > 0)
    finite = strain[np.isfinite(strain)]
    peak = float(finite.max()) if len(finite) else 0.0
    lowest = thresholds[0] if thresholds else max(peak, 1e-3)
    bottom = lowest * _STRAIN_FLOOR
    top = 6.0 * max(peak, thresholds[-1] if thresholds else 0.0, bottom * 10.0)  # legend room
    ax.set_yscale("log", nonpositive="clip")
    plain = FuncFormatter(_plain_number)  # 0.01, 0.1, 1: no mathtext powers of ten to typeset
    ax.yaxis.set_major_formatter(plain)
    if len(d):
        idx = _envelope(strain)
        x = d[idx] / dscale
        band_lo = np.maximum(strain[idx] - sigma[idx], bottom)
        ax.fill_between(x, band_lo, strain[idx] + sigma[idx], color="tab:blue", alpha=0.25,
                        lw=0, label="+-1 sigma")  # fmt: skip
        ax.plot(x, np.maximum(strain[idx], bottom), "-", color="k", lw=1.0,
                label="bending strain")  # fmt: skip
    else:
        ax.text(0.5, 0.5, "no curvature profile", ha="center", va="center",
                transform=ax.transAxes)  # fmt: skip
    for k, th in enumerate(thresholds):
        ax.axhline(th, color="tab:red", ls="--" if k else ":", lw=1.0,
                   label=f"threshold {th:g} %")  # fmt: skip
    feats = [f for f in integrity.features if np.isfinite(f.start_m) and np.isfinite(f.end_m)]
    if feats:
        ax.hlines([f.threshold_pct for f in feats], [f.start_m / dscale for f in feats],
                  [f.end_m / dscale for f in feats], colors="tab:red", lw=5, alpha=0.6,
                  label="strain features")  # fmt: skip
    bends = list(integrity.bends)
    if bends:
        apex = np.array([b.apex_m for b in bends], dtype=np.float64)
        at = np.interp(apex, d, strain) if len(d) else np.full(len(apex), bottom)
        at = np.maximum(np.where(np.isfinite(at), at, bottom), bottom)
        ax.vlines(apex / dscale, 0.0, 1.0, transform=ax.get_xaxis_transform(),
                  colors="tab:orange", lw=0.8, alpha=0.5)  # fmt: skip
        ax.plot(apex / dscale, at, "v", color="tab:orange", ms=6, label="bends (apex)")
        step = max(1, -(-len(bends) // _MAX_BEND_LABELS))
        for b, x, y in list(zip(bends, apex, at, strict=True))[::step]:
            ax.annotate(str(b.number), (x / dscale, y), textcoords="offset points",
                        xytext=(0, 6), ha="center", fontsize=7, color="tab:orange")  # fmt: skip
    ax.set_ylim(bottom, top)
    ax.yaxis.set_minor_locator(NullLocator())  # log minor ticks cost a third of the figure
    ax.set_xlabel(f"chainage [{dunit}]")
    ax.set_ylabel("bending strain [%]")
    to_curv = 2e3 / (100.0 * integrity.outer_diameter) if integrity.outer_diameter > 0 else 0.0
    if to_curv > 0:
        sec = ax.secondary_yaxis("right", functions=(lambda s: s * to_curv,
                                                     lambda k: k / to_curv))  # fmt: skip
        sec.set_ylabel("curvature [1/km]")
        sec.yaxis.set_major_formatter(plain)
        sec.yaxis.set_minor_locator(NullLocator())
    ax.set_title(
        f"Bending strain (outer diameter {integrity.outer_diameter:g} m, window "
        f"{integrity.window:.2f} m): {len(bends)} bends, {len(integrity.features)} strain "
        "features; bends numbered at their apex",
        y=TITLE_Y,
    )
    ax.grid(True, alpha=0.3, which="major")
    ax.legend(loc="upper right", fontsize=8, ncol=3)


# figures made ahead (prepare_figure), by whether they have the strain panel
_SPARE: dict[bool, tuple[Any, Any, Any]] = {}


def _figure(with_strain: bool) -> tuple[Any, Any, Any]:
    """(figure, 2x2 array of the four panels' axes, the strain panel's axes or None), with
    fixed margins (a layout engine would draw the figure twice)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not with_strain:
        fig = Figure(figsize=(14, 10), dpi=100)
        FigureCanvasAgg(fig)
        axs = fig.subplots(2, 2, gridspec_kw=dict(left=0.06, right=0.98, bottom=0.08, top=0.92,
                                                  wspace=0.18, hspace=0.32))  # fmt: skip
        return fig, axs, None
    fig = Figure(figsize=(14, 14.5), dpi=100)
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(3, 2, left=0.06, right=0.95, bottom=0.05, top=0.94, wspace=0.18,
                          hspace=0.32)  # fmt: skip
    axs = np.array([[fig.add_subplot(gs[r, c]) for c in range(2)] for r in range(2)])
    return fig, axs, fig.add_subplot(gs[2, :])


def prepare_figure(with_strain: bool = True) -> None:
    """Make the next report's empty figure now (its axes are a tenth of drawing it), for a
    process that waits for its data (plot_process); the next :func:`plot_report` of that
    layout uses it."""
    fig, axs, strain_ax = _figure(with_strain)
    for ax in [*axs.flat, *([strain_ax] if strain_ax is not None else [])]:
        for axis in (ax.xaxis, ax.yaxis):
            axis.get_major_ticks(_TICKS_AHEAD)  # made on the first draw else, a fifth of it
    _SPARE[with_strain] = fig, axs, strain_ax


def marker_residuals_enu(
    traj: Trajectory, datum: Datum, markers: Sequence[Marker]
) -> NDArray[np.float64]:
    """(M, 3) estimate minus survey at each marker, ENU metres: the trajectory interpolated at
    the passage time minus the surveyed position (both in the datum's ENU frame)."""
    if not markers or len(traj.t) == 0:
        return np.zeros((0, 3))
    t = np.array([m.t for m in markers])
    est = interpolate_trajectory(traj, t)
    e_est = geodetic_to_enu(est.lat, est.lon, est.h, datum.lat, datum.lon, datum.alt)
    e_srv = geodetic_to_enu(
        np.array([m.lat for m in markers]),
        np.array([m.lon for m in markers]),
        np.array([m.alt for m in markers]),
        datum.lat,
        datum.lon,
        datum.alt,
    )
    return np.asarray(e_est - e_srv, dtype=np.float64).reshape(-1, 3)


def plot_report(
    png_path: str | os.PathLike[str],
    traj: Trajectory,
    datum: Datum,
    markers: Sequence[Marker] = (),
    marker_residuals: ArrayLike | None = None,
    title: str = "",
    integrity: IntegrityReport | None = None,
) -> None:
    """Write the four-panel report PNG (see the module docstring) atomically to ``png_path``.

    traj: the centreline (any sampling; long ones are decimated for drawing); datum: origin of
    the ENU frame; markers: surveyed markers (their passage times place them on the chainage);
    marker_residuals: (M, 3) estimate minus survey, ENU m, one row per marker -- computed from
    traj when None; integrity: the run's integrity products
    (:class:`~pipe_nav_core.products.integrity.IntegrityReport`), which add the strain panel.
    """
    markers = list(markers)
    n = len(traj.t)
    enu = (
        np.asarray(
            geodetic_to_enu(traj.lat, traj.lon, traj.h, datum.lat, datum.lon, datum.alt)
        ).reshape(n, 3)
        if n
        else np.zeros((0, 3))
    )
    dist = np.asarray(traj.distance, dtype=np.float64).reshape(n)
    sig = (
        np.asarray(traj.sigma_enu, dtype=np.float64).reshape(n, 3)
        if traj.sigma_enu is not None
        else None
    )
    idx = _decimate(n)
    if markers:
        m_enu = np.asarray(
            geodetic_to_enu(
                np.array([m.lat for m in markers]),
                np.array([m.lon for m in markers]),
                np.array([m.alt for m in markers]),
                datum.lat,
                datum.lon,
                datum.alt,
            )
        ).reshape(-1, 3)
        m_dist = np.interp([m.t for m in markers], traj.t, dist) if n else np.zeros(len(markers))
    else:
        m_enu = np.zeros((0, 3))
        m_dist = np.zeros(0)
    if marker_residuals is None:
        res = marker_residuals_enu(traj, datum, markers)
    else:
        res = np.asarray(marker_residuals, dtype=np.float64).reshape(-1, 3)

    extent = float(np.ptp(enu[:, :2])) if n else 0.0
    scale, unit = (1000.0, "km") if extent > 5000.0 else (1.0, "m")
    dscale, dunit = (1000.0, "km") if (n and np.nanmax(np.abs(dist)) > 5000.0) else (1.0, "m")

    fig, axs, strain_ax = _SPARE.pop(integrity is not None, None) or _figure(integrity is not None)
    if integrity is not None:
        _strain_panel(strain_ax, integrity, dscale, dunit)
    fig.suptitle(title or "PipeNav centreline report", fontsize=14)

    # 1. plan view
    ax = axs[0, 0]
    if n:
        ax.plot(
            enu[idx, 0] / scale, enu[idx, 1] / scale, "-", color="k", lw=1.2, label="centreline"
        )
        ax.plot(enu[0, 0] / scale, enu[0, 1] / scale, "o", color="tab:green", label="start")
        ax.plot(enu[-1, 0] / scale, enu[-1, 1] / scale, "s", color="tab:red", label="end")
    if len(m_enu):
        ax.plot(
            m_enu[:, 0] / scale,
            m_enu[:, 1] / scale,
            "^",
            color="tab:purple",
            ms=7,
            label="markers (survey)",
        )
        if len(markers) <= 40:
            for m, p in zip(markers, m_enu, strict=True):
                ax.annotate(
                    m.name,
                    (p[0] / scale, p[1] / scale),
                    textcoords="offset points",
                    xytext=(4, 4),
                    fontsize=7,
                    color="tab:purple",
                )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"east [{unit}]")
    ax.set_ylabel(f"north [{unit}]")
    ax.set_title("Plan view (map frame, ENU about the datum)", y=TITLE_Y)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)

    # 2. elevation profile with 3-sigma band
    ax = axs[0, 1]
    if n:
        d = dist[idx] / dscale
        up = enu[idx, 2]
        if sig is not None:
            s3 = 3.0 * sig[idx, 2]
            ax.fill_between(
                d, up - s3, up + s3, color="tab:green", alpha=0.25, label="+-3 sigma (up)"
            )
        ax.plot(d, up, "-", color="k", lw=1.2, label="up")
    if len(m_enu):
        ax.plot(
            m_dist / dscale, m_enu[:, 2], "^", color="tab:purple", ms=7, label="markers (survey)"
        )
    ax.set_xlabel(f"chainage [{dunit}]")
    ax.set_ylabel("up [m]")
    ax.set_title("Elevation profile", y=TITLE_Y)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)

    # 3. sigma along chainage
    ax = axs[1, 0]
    if n and sig is not None:
        d = dist[idx] / dscale
        ax.plot(
            d,
            np.hypot(sig[idx, 0], sig[idx, 1]),
            "-",
            color="tab:blue",
            label="horizontal (sqrt(sE^2 + sN^2))",
        )
        ax.plot(d, sig[idx, 2], "-", color="tab:green", label="vertical (sU)")
        for md in m_dist:
            ax.axvline(md / dscale, color="tab:purple", alpha=0.25, lw=0.8)
        ax.legend(loc="upper right", fontsize=8)
    else:
        ax.text(
            0.5,
            0.5,
            "no uncertainty in this trajectory",
            ha="center",
            va="center",
            transform=ax.transAxes,
        )
    ax.set_xlabel(f"chainage [{dunit}]")
    ax.set_ylabel("1 sigma [m]")
    ax.set_title("Position uncertainty (1 sigma); markers as vertical lines", y=TITLE_Y)
    ax.grid(True, alpha=0.3)

    # 4. residuals at markers
    ax = axs[1, 1]
    if len(res):
        k = np.arange(len(res))
        errs = None
        if sig is not None and n and markers and len(markers) == len(res):
            est = interpolate_trajectory(traj, [m.t for m in markers])
            errs = 3.0 * np.asarray(est.sigma_enu).reshape(-1, 3)
        big = np.nanmax(np.abs(res)) if np.isfinite(res).any() else 0.0
        rs, ru = (100.0, "cm") if big < 1.0 else (1.0, "m")
        for j, (c, off) in enumerate(zip("enu", (-0.2, 0.0, 0.2), strict=True)):
            ax.errorbar(
                k + off,
                res[:, j] * rs,
                yerr=None if errs is None else errs[:, j] * rs,
                fmt="o",
                ms=5,
                capsize=2,
                color=_COLORS[c],
                label=f"{c.upper()}" + (" (+-3 sigma est.)" if errs is not None else ""),
            )
        ax.axhline(0.0, color="k", lw=0.8)
        names = [m.name for m in markers] if len(markers) == len(res) else [str(i) for i in k]
        step = max(1, len(k) // 30)
        ax.set_xticks(k[::step])
        ax.set_xticklabels(names[::step], rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(f"estimate - survey [{ru}]")
        ax.legend(loc="upper right", fontsize=8)
    else:
        ax.text(0.5, 0.5, "no markers", ha="center", va="center", transform=ax.transAxes)
    ax.set_title("Residual at markers (estimate minus survey, ENU)", y=TITLE_Y)
    ax.grid(True, alpha=0.3)

    with atomic_write(png_path, "wb") as f:
        fig.savefig(f, format="png", pil_kwargs={"compress_level": 1})  # 3x faster, 1.5x larger
