"""Run-to-run comparison: has the pipe moved between two inspection runs?

Two smoothed runs through one pipe (A, the earlier, and B) are aligned by their girth welds
(the joint-length sequences matched by :func:`pipe_nav_core.products.joints.align_sequences`,
tolerant to missed and extra welds and to a scale error), and by their bends where welds are
missing (a run without a magnetometer, or a stretch longer than ``bend_gap`` m without a matched
weld). Each matched weld (or bend apex) is one physical point of the pipe seen twice; per point:

- the 3-D displacement d = B - A (east, north, up, m) in run A's ``map`` frame;
- its sigma per axis, sqrt(sigma_A^2 + sigma_B^2), from each run's smoothed position sigma at the
  point (``sigma_enu`` of the centreline: it covers each run's slowly varying, marker-tied
  error, which is what makes two runs through an unmoved pipe disagree by a few centimetres)
  plus the along-pipe uncertainty of the weld's chainage (``sigma_distance``) along the axis;
- the change of curvature (vertical, horizontal, 1/m) and of bending strain (percent) between the
  runs, the largest change over the stretch the point stands for (halfway to its neighbours),
  from :func:`pipe_nav_core.products.integrity_report` of each run on a common chainage;
- ``significant``: the displacement is over ``n_sigma`` (3) sigma -- as a 3-D test, its
  Mahalanobis length over the chi-square(3) quantile of the two-sided n-sigma probability, so
  that a run through an unmoved pipe flags about 0.3 % of its welds, not 3 % -- AND longer than
  ``threshold`` m (default 5 cm).

Consecutive significant points form the movement intervals (start, end, peak). No NaN leaves
this module: unknown values are 0 with a note.

About 400 lines, one module on purpose: the alignment of two runs and the displacement
statistics on it are one computation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.kalman import chi2_threshold
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.products.integrity import IntegrityReport, integrity_report
from pipe_nav_core.types import Datum, Trajectory

if TYPE_CHECKING:
    from pipe_nav_core.products.welds import Weld

FloatArray = NDArray[np.float64]

MOVEMENT_THRESHOLD_M = 0.05  # smallest displacement reported as movement, m
MOVEMENT_N_SIGMA = 3.0  # and over this many sigma
BEND_GAP_M = 50.0  # bends anchor the comparison where no matched weld is this close, m
BEND_TOLERANCE_M = 5.0  # bend apexes of the two runs this close (after weld alignment) match, m
MIN_WELD_PAIRS = 3  # fewer matched welds: the runs are aligned by their bends only


class RunLike(Protocol):
    """What a comparison needs of one run (io.smoothed_bag.SmoothedRun has it): the smoothed
    centreline (with ``sigma_enu`` when known), the datum of its ``map`` frame, its welds."""

    trajectory: Trajectory
    datum: Datum
    welds: Sequence[Weld]


@dataclass(frozen=True)
class PointMovement:
    """One physical point of the pipe (a matched weld, or a bend apex) in both runs.

    weld / weld_b: weld numbers in A and B (bend numbers when anchor is ``bend``);
    distance / distance_b: chainage in A and in B, m; lat, lon (rad), alt (m): position in A;
    d_enu: (3,) B - A in A's map frame, m; sigma_enu: (3,) its one-sigma, m; mahalanobis: the
    displacement's length in sigmas (3-D); d_curvature_vertical / d_curvature_horizontal: 1/m
    and d_strain_pct: percent, B - A, the largest change near the point.
    """

    weld: int
    weld_b: int
    anchor: str
    distance: float
    distance_b: float
    lat: float
    lon: float
    alt: float
    d_enu: FloatArray
    sigma_enu: FloatArray
    mahalanobis: float
    d_curvature_vertical: float
    d_curvature_horizontal: float
    d_strain_pct: float
    significant: bool

    @property
    def magnitude(self) -> float:
        """3-D displacement length, m."""
        return float(np.linalg.norm(self.d_enu))


@dataclass(frozen=True)
class MovementInterval:
    """A stretch of consecutive significant points: chainages in A (m), the peak point's
    chainage, displacement (3,) m and its sigma (3,) m, and how many points it holds."""

    number: int
    start_m: float
    end_m: float
    peak_m: float
    peak_d_enu: FloatArray
    peak_sigma_enu: FloatArray
    points: int

    @property
    def peak_magnitude(self) -> float:
        return float(np.linalg.norm(self.peak_d_enu))


@dataclass(frozen=True)
class MovementReport:
    """The comparison of run B against run A (A's map frame and chainage)."""

    points: list[PointMovement]
    intervals: list[MovementInterval]
    datum: Datum
    threshold: float
    n_sigma: float
    weld_pairs: int
    bend_pairs: int
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, object]:
        """Figures for people."""
        mags = [p.magnitude for p in self.points]
        return {
            "points": len(self.points),
            "weld_pairs": self.weld_pairs,
            "bend_pairs": self.bend_pairs,
            "intervals": len(self.intervals),
            "max_displacement_m": max(mags) if mags else 0.0,
            "threshold_m": self.threshold,
            "n_sigma": self.n_sigma,
            "notes": list(self.notes),
        }


def align_welds(a: Sequence[float], b: Sequence[float]) -> list[tuple[int, int]]:
    """Matched index pairs of two weld chainage lists (m), by the joint-length sequences."""
    from pipe_nav_core.products.joints import align_sequences

    return [(int(i), int(j)) for i, j in align_sequences(a, b)]


def chainage_map(anchors_a: FloatArray, anchors_b: FloatArray):  # noqa: ANN201
    """s_A (m) -> s_B (m) through matched anchors: piecewise linear, offset-continued beyond
    the first and last anchor (scale 1). No anchors: the identity."""
    aa = np.asarray(anchors_a, dtype=np.float64)
    bb = np.asarray(anchors_b, dtype=np.float64)
    if len(aa) == 0:
        return lambda s: np.asarray(s, dtype=np.float64)
    order = np.argsort(aa)
    aa, bb = aa[order], bb[order]

    def f(s: FloatArray) -> FloatArray:
        s = np.asarray(s, dtype=np.float64)
        out = np.interp(s, aa, bb)
        out = np.where(s < aa[0], s - aa[0] + bb[0], out)
        return np.where(s > aa[-1], s - aa[-1] + bb[-1], out)

    return f


def _sigma_at(traj: Trajectory, s: FloatArray, fallback: FloatArray) -> FloatArray:
    """Smoothed position sigma (N, 3) m at chainages s; ``fallback`` (N, 3) where unknown."""
    if traj.sigma_enu is None:
        return fallback
    sig = np.asarray(traj.sigma_enu, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(traj.distance, dtype=np.float64)
    ok = np.isfinite(sig).all(axis=1) & np.isfinite(d)
    if ok.sum() < 2:
        return fallback
    order = np.argsort(d[ok], kind="stable")
    return np.column_stack([np.interp(s, d[ok][order], sig[ok][order, k]) for k in range(3)])


def _axis_at(traj: Trajectory, datum: Datum, s: FloatArray) -> FloatArray:
    """Unit pipe axis (N, 3) in the map frame of ``datum`` at chainages s (m)."""
    d = np.asarray(traj.distance, dtype=np.float64)
    enu = geodetic_to_enu(traj.lat, traj.lon, traj.h, datum.lat, datum.lon, datum.alt)
    enu = np.asarray(enu).reshape(-1, 3)
    ds = 1.0
    ahead = np.column_stack([np.interp(s + ds, d, enu[:, k]) for k in range(3)])
    behind = np.column_stack([np.interp(s - ds, d, enu[:, k]) for k in range(3)])
    v = ahead - behind
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0)


def _points_of(items: Sequence[Any]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(chainage (N,), geodetic (N, 3) rad/rad/m, sigma (N, 3): h/sqrt2, h/sqrt2, v, and
    sigma_distance (N,)) of welds or bends."""
    s = np.array([float(getattr(w, "distance", getattr(w, "apex_m", 0.0))) for w in items])
    geo = np.array([[w.lat, w.lon, w.alt] for w in items], dtype=np.float64).reshape(-1, 3)
    sig = np.array([[getattr(w, "sigma_h", 0.0), getattr(w, "sigma_v", 0.0),
                     getattr(w, "sigma_distance", 0.0)] for w in items],
                   dtype=np.float64).reshape(-1, 3)  # fmt: skip
    sig = np.where(np.isfinite(sig), sig, 0.0)
    return s, geo, sig


def _match_bends(sa: FloatArray, sb_in_a: FloatArray, tolerance: float) -> list[tuple[int, int]]:
    """Greedy one-to-one pairs of bend apexes within ``tolerance`` m (B mapped onto A)."""
    if len(sa) == 0 or len(sb_in_a) == 0:
        return []
    dist = np.abs(sa[:, None] - sb_in_a[None, :])
    pairs: list[tuple[int, int]] = []
    used_a, used_b = set(), set()
    for flat in np.argsort(dist, axis=None):
        i, j = divmod(int(flat), len(sb_in_a))
        if dist[i, j] > tolerance:
            break
        if i in used_a or j in used_b:
            continue
        pairs.append((i, j))
        used_a.add(i)
        used_b.add(j)
    return sorted(pairs)


def _largest_change(
    s: FloatArray, change: FloatArray, lo: FloatArray, hi: FloatArray
) -> FloatArray:
    """Per stretch [lo, hi]: the value of ``change`` (sampled at increasing s) of largest
    magnitude (the nearest sample when the stretch holds none)."""
    out = np.zeros(len(lo))
    for k, (a, b) in enumerate(zip(lo, hi, strict=True)):
        i0, i1 = np.searchsorted(s, a, "left"), np.searchsorted(s, b, "right")
        if i1 > i0:
            seg = change[i0:i1]
            out[k] = seg[np.argmax(np.abs(seg))]
        elif len(s):
            out[k] = change[min(int(np.searchsorted(s, 0.5 * (a + b))), len(s) - 1)]
    return out


def compare_runs(
    run_a: RunLike,
    run_b: RunLike,
    config: NavConfig | None = None,
    *,
    threshold: float = MOVEMENT_THRESHOLD_M,
    n_sigma: float = MOVEMENT_N_SIGMA,
    bend_gap: float = BEND_GAP_M,
    bend_tolerance: float = BEND_TOLERANCE_M,
    reports: tuple[IntegrityReport, IntegrityReport] | None = None,
) -> MovementReport:
    """Compare run B with run A (see the module docstring). config: settings of the curvature
    and bend products (default NavConfig()); reports: both runs' integrity reports when already
    computed (e.g. in parallel by :mod:`pipe_nav_core.app.runs`). threshold m, n_sigma, bend_gap m,
    bend_tolerance m as in the module docstring."""
    if not threshold >= 0.0 or not math.isfinite(threshold):
        raise ValueError(f"movement threshold must be >= 0 m, not {threshold}")
    if not n_sigma > 0.0 or not math.isfinite(n_sigma):
        raise ValueError(f"movement n_sigma must be positive, not {n_sigma}")
    cfg = config if config is not None else NavConfig()
    notes: list[str] = []
    if reports is None:
        reports = (integrity_report(run_a.trajectory, cfg),
                   integrity_report(run_b.trajectory, cfg))  # fmt: skip
    rep_a, rep_b = reports
    datum = run_a.datum

    # 1. welds: the joint-length sequences
    wa, wb = list(run_a.welds), list(run_b.welds)
    sa_w, geo_a_w, sig_a_w = _points_of(wa)
    sb_w, geo_b_w, sig_b_w = _points_of(wb)
    weld_pairs = align_welds(sa_w, sb_w) if len(wa) and len(wb) else []
    if len(weld_pairs) < MIN_WELD_PAIRS:
        if wa or wb:
            notes.append(f"only {len(weld_pairs)} welds matched: aligned by the bends")
        else:
            notes.append("no welds in the runs: aligned by the bends")
        weld_pairs = []
    ia = np.array([i for i, _ in weld_pairs], dtype=np.int64)
    ib = np.array([j for _, j in weld_pairs], dtype=np.int64)
    to_b = chainage_map(sa_w[ia], sb_w[ib])

    # 2. bends where no matched weld is near (or everywhere without welds)
    ba, bb = rep_a.bends, rep_b.bends
    sa_b, geo_a_b, sig_a_b = _points_of(ba)
    sb_b, geo_b_b, sig_b_b = _points_of(bb)
    to_a = chainage_map(sb_w[ib], sa_w[ia])
    bend_pairs = _match_bends(sa_b, to_a(sb_b), bend_tolerance)
    if len(ia):
        near = np.min(np.abs(sa_b[[i for i, _ in bend_pairs]][:, None] - sa_w[ia][None, :]),
                      axis=1) if bend_pairs else np.zeros(0)  # fmt: skip
        bend_pairs = [p for p, dn in zip(bend_pairs, near, strict=True) if dn > bend_gap]
    if not weld_pairs and bend_pairs:
        # without welds the bends are the chainage anchors too
        to_b = chainage_map(sa_b[[i for i, _ in bend_pairs]], sb_b[[j for _, j in bend_pairs]])
    if not weld_pairs and not bend_pairs:
        notes.append("no welds or bends matched between the runs: nothing to compare")

    # 3. the points: weld pairs then bend pairs, in A's chainage order
    kinds = ["weld"] * len(weld_pairs) + ["bend"] * len(bend_pairs)
    num_a = [wa[i].number for i, _ in weld_pairs] + [ba[i].number for i, _ in bend_pairs]
    num_b = [wb[j].number for _, j in weld_pairs] + [bb[j].number for _, j in bend_pairs]
    bi = np.array([i for i, _ in bend_pairs], dtype=np.int64)
    bj = np.array([j for _, j in bend_pairs], dtype=np.int64)
    s_a = np.concatenate([sa_w[ia], sa_b[bi]])
    s_b = np.concatenate([sb_w[ib], sb_b[bj]])
    geo_a = np.concatenate([geo_a_w[ia], geo_a_b[bi]])
    geo_b = np.concatenate([geo_b_w[ib], geo_b_b[bj]])
    own_a = np.concatenate([sig_a_w[ia], sig_a_b[bi]])
    own_b = np.concatenate([sig_b_w[ib], sig_b_b[bj]])
    order = np.argsort(s_a, kind="stable")
    kinds = [kinds[k] for k in order]
    num_a = [int(num_a[k]) for k in order]
    num_b = [int(num_b[k]) for k in order]
    s_a, s_b, geo_a, geo_b = s_a[order], s_b[order], geo_a[order], geo_b[order]
    own_a, own_b = own_a[order], own_b[order]
    n = len(s_a)

    pa = geodetic_to_enu(geo_a[:, 0], geo_a[:, 1], geo_a[:, 2], datum.lat, datum.lon,
                         datum.alt).reshape(-1, 3)  # fmt: skip
    pb = geodetic_to_enu(geo_b[:, 0], geo_b[:, 1], geo_b[:, 2], datum.lat, datum.lon,
                         datum.alt).reshape(-1, 3)  # fmt: skip
    d = pb - pa

    def sigma_of(run: RunLike, s: FloatArray, own: FloatArray) -> FloatArray:
        fb = np.column_stack([own[:, 0] / math.sqrt(2.0), own[:, 0] / math.sqrt(2.0), own[:, 1]])
        sig = _sigma_at(run.trajectory, s, fb)
        along = own[:, 2:3] * _axis_at(run.trajectory, run.datum, s)  # chainage uncertainty
        return np.sqrt(sig**2 + along**2)

    if n:
        if run_a.trajectory.sigma_enu is None or run_b.trajectory.sigma_enu is None:
            notes.append("a run has no centreline sigmas: the welds' own sigmas are used")
        sigma = np.sqrt(sigma_of(run_a, s_a, own_a) ** 2 + sigma_of(run_b, s_b, own_b) ** 2)
        sigma = np.maximum(sigma, 1e-4)  # a floor: never divide by zero
    else:
        sigma = np.zeros((0, 3))
    maha = np.sqrt(np.sum((d / sigma) ** 2, axis=1)) if n else np.zeros(0)
    two_sided = math.erf(n_sigma / math.sqrt(2.0))
    bound = math.sqrt(chi2_threshold(two_sided, 3))
    significant = (maha > bound) & (np.linalg.norm(d, axis=1) > threshold)

    # 4. curvature and strain change on A's chainage
    pa_, pb_ = rep_a.profile, rep_b.profile
    if n and len(pa_) > 1 and len(pb_) > 1:
        sp = pa_.distance
        sbp = to_b(sp)
        kv = np.interp(sbp, pb_.distance, pb_.vertical) - pa_.vertical
        kh = np.interp(sbp, pb_.distance, pb_.horizontal) - pa_.horizontal
        ds = np.interp(sbp, pb_.distance, rep_b.strain_pct) - rep_a.strain_pct
        mid = 0.5 * (s_a[1:] + s_a[:-1])
        lo = np.concatenate([[s_a[0] - 6.0], mid])
        hi = np.concatenate([mid, [s_a[-1] + 6.0]])
        dkv, dkh, dst = (_largest_change(sp, c, lo, hi) for c in (kv, kh, ds))
    else:
        dkv = dkh = dst = np.zeros(n)

    points = [
        PointMovement(weld=num_a[k], weld_b=num_b[k], anchor=kinds[k], distance=float(s_a[k]),
                      distance_b=float(s_b[k]), lat=float(geo_a[k, 0]), lon=float(geo_a[k, 1]),
                      alt=float(geo_a[k, 2]), d_enu=d[k].copy(), sigma_enu=sigma[k].copy(),
                      mahalanobis=float(maha[k]), d_curvature_vertical=float(dkv[k]),
                      d_curvature_horizontal=float(dkh[k]), d_strain_pct=float(dst[k]),
                      significant=bool(significant[k]))
        for k in range(n)
    ]  # fmt: skip
    return MovementReport(points, movement_intervals(points), datum, float(threshold),
                          float(n_sigma), len(weld_pairs), len(bend_pairs), notes)  # fmt: skip


def movement_intervals(points: Sequence[PointMovement]) -> list[MovementInterval]:
    """Runs of consecutive significant points (in chainage order) as intervals."""
    out: list[MovementInterval] = []
    k = 0
    while k < len(points):
        if not points[k].significant:
            k += 1
            continue
        j = k
        while j + 1 < len(points) and points[j + 1].significant:
            j += 1
        run = points[k : j + 1]
        peak = max(run, key=lambda p: p.magnitude)
        out.append(MovementInterval(len(out) + 1, run[0].distance, run[-1].distance,
                                    peak.distance, peak.d_enu, peak.sigma_enu,
                                    len(run)))  # fmt: skip
        k = j + 1
    return out


__all__ = [
    "BEND_GAP_M",
    "BEND_TOLERANCE_M",
    "MOVEMENT_N_SIGMA",
    "MOVEMENT_THRESHOLD_M",
    "MovementInterval",
    "MovementReport",
    "PointMovement",
    "RunLike",
    "align_welds",
    "chainage_map",
    "compare_runs",
    "movement_intervals",
]
