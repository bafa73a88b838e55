"""The bend list: where the pipe bends, by how much, how sharply, which way, and what kind.

A bend is a stretch of the curvature profile above the bend threshold (curvature over
1 / ``bend_threshold_radius``) whose direction does not reverse (an S, or the two sides of a dip,
is two bends), listed when its 3-D angle reaches ``bend_min_angle``. Stretches of one direction
split only by noise dipping under the threshold for less than a window are one bend.

- angle: between the axis before and after the bend, taken where the curvature has fallen to a
  quarter of the threshold (or reverses, or half-way to the next bend), so that the ramps of
  an elastic bend are not lost; its sigma from the IMU noise model over that stretch.
- apex: the middle of the stretch where the curvature is over half its peak (the middle of a
  circular arc, ramps and all). start and end: the first and last rows of the stretch, widened
  to the apex where a bend shorter than the rows' spacing has its apex beyond them.
- radius: 1 / the peak curvature on a profile whose window is a quarter of that stretch (at
  least four track steps), narrowed while the stretch shrinks with it, so that a bend shorter
  than the profile's window is not reported wider than it is, and a long elastic bend is
  measured over a window long enough that noise does not bias its peak; its sigma from that
  profile's sigma.
- direction and plane from the vertical and horizontal components of the curvature integrated
  over the bend; class by radius in outer diameters (``bend_class_limits``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.geo.attitude import quat_from_euler
from pipe_nav_core.model.sensors import ImuSpec
from pipe_nav_core.products.curvature import (
    AxisTrack,
    CurvatureProfile,
    relative_angle_sigma,
    windowed_curvature,
)

FloatArray = NDArray[np.float64]

BEND_CLASSES = ("elbow", "induction", "field", "elastic")
APEX_STEP_M = 0.1  # m, at most this between the points where apex and radius are looked for


@dataclass(frozen=True)
class PipeBend:
    """One bend. Chainages m of distance_m; lat, lon rad, alt m (WGS84, apex); angle, plane,
    sigma_angle rad; radius, sigma_radius m; radius_d in outer diameters; direction ``left``,
    ``right``, ``over``, ``sag`` or ``sag+left`` style; kind one of BEND_CLASSES; apex_t s;
    apex_quat_nb [x, y, z, w] with x along the pipe axis at the apex (ENU, no roll);
    radius_resolved: False when the bend is shorter than the track resolves (a few cm): its
    radius is then at most ``radius`` (sigma_radius = radius); sigma_h, sigma_v: m, one-sigma
    horizontal and vertical position of the apex (the smoothed centreline's)."""

    number: int
    start_m: float
    apex_m: float
    end_m: float
    lat: float
    lon: float
    alt: float
    angle: float
    sigma_angle: float
    radius: float
    sigma_radius: float
    radius_d: float
    plane: float
    direction: str
    kind: str
    apex_t: float
    apex_quat_nb: tuple[float, float, float, float]
    radius_resolved: bool = True
    sigma_h: float = float("nan")
    sigma_v: float = float("nan")


def bend_class(radius_d: float, limits: tuple[float, float, float]) -> str:
    """``elbow`` / ``induction`` / ``field`` / ``elastic`` by the radius in outer diameters."""
    return BEND_CLASSES[int(np.searchsorted(np.asarray(limits), radius_d, side="right"))]


def bend_direction(vertical: float, horizontal: float) -> str:
    """The direction word of a bend from its integrated vertical and horizontal turns (rad)."""
    v = "sag" if vertical > 0 else "over"
    h = "right" if horizontal > 0 else "left"
    total = math.hypot(vertical, horizontal)
    if min(abs(vertical), abs(horizontal)) >= 0.25 * total:
        return f"{v}+{h}"
    return v if abs(vertical) >= abs(horizontal) else h


def _stretches(profile: CurvatureProfile, threshold: float) -> list[tuple[int, int]]:
    """Index ranges [i0, i1] over the threshold with one curvature direction, joined across
    dips shorter than a window that keep the direction."""
    k = np.stack([profile.vertical, profile.horizontal], axis=1)
    above = profile.total > threshold
    out: list[tuple[int, int]] = []
    i, n = 0, len(above)
    while i < n:
        if not above[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and above[j + 1] and k[j + 1] @ k[j] > 0:
            j += 1
        out.append((i, j))
        i = j + 1
    joined: list[tuple[int, int]] = []
    for a, b in out:
        if joined:
            pa, pb = joined[-1]
            gap = profile.distance[a] - profile.distance[pb]
            same = k[pa : pb + 1].sum(axis=0) @ k[a : b + 1].sum(axis=0) > 0
            if gap <= profile.window and same:
                joined[-1] = (pa, b)
                continue
        joined.append((a, b))
    return joined


def _extend(
    profile: CurvatureProfile, a: int, b: int, lo: int, hi: int, level: float
) -> tuple[int, int]:
    """Widen [a, b] within [lo, hi] while the curvature stays over ``level`` in its direction."""
    k = np.stack([profile.vertical, profile.horizontal], axis=1)
    d = k[a : b + 1].sum(axis=0)
    while a > lo and profile.total[a - 1] > level and k[a - 1] @ d > 0:
        a -= 1
    while b < hi and profile.total[b + 1] > level and k[b + 1] @ d > 0:
        b += 1
    return a, b


def find_bends(
    profile: CurvatureProfile,
    track: AxisTrack,
    spec: ImuSpec,
    *,
    threshold_radius: float,
    min_angle: float,
    outer_diameter: float,
    class_limits: tuple[float, float, float],
) -> list[PipeBend]:
    """The bends of a curvature profile (see the module), numbered 1, 2, ... in chainage order."""
    if len(profile) < 2:
        return []
    stretches = _stretches(profile, 1.0 / threshold_radius)
    k = np.stack([profile.vertical, profile.horizontal], axis=1)
    d = profile.distance
    junctions = [_junction(k, d, stretches[i], stretches[i + 1]) for i in range(len(stretches) - 1)]
    n = len(profile)
    floor = 4.0 * float(np.median(np.diff(track.arc)))  # m: the shortest arc the track resolves
    ends: list[tuple[float, float]] = []  # per stretch, the chainages of the axis before and after
    for idx, (a, b) in enumerate(stretches):
        lo = 0 if idx == 0 else (stretches[idx - 1][1] + a + 1) // 2
        hi = n - 1 if idx == len(stretches) - 1 else (b + stretches[idx + 1][0]) // 2
        ea, eb = _extend(profile, a, b, lo, hi, 0.25 / threshold_radius)
        # the axis before and after: at the first rows outside (their window barely touches
        # the bend), or where the curvature reverses towards the neighbouring bend
        before = float(d[max(ea - 1, 0)])
        after = float(d[min(eb + 1, n - 1)])
        if idx > 0:
            before = max(before, junctions[idx - 1])
        if idx < len(junctions):
            after = min(after, junctions[idx])
        ends.append((before, after))
    apexes = _apexes(profile, track, spec, stretches, floor)
    bends: list[PipeBend] = []
    for (a, b), around, apex in zip(stretches, ends, apexes, strict=True):
        if apex is None:
            continue
        bend = _measure(profile, track, spec, a, b, around, apex, outer_diameter, class_limits,
                        floor)  # fmt: skip
        if bend.angle >= min_angle - 1e-9:
            bends.append(bend)
    return [replace(b, number=i + 1) for i, b in enumerate(bends)]


def _junction(
    k: FloatArray, d: FloatArray, first: tuple[int, int], second: tuple[int, int]
) -> float:
    """Chainage (m) between two stretches where the curvature turns from the first's direction
    (linear between rows), else half-way between them."""
    a, b = first
    direction = k[a : b + 1].sum(axis=0)
    along = k[b : second[0] + 1] @ direction
    r = np.flatnonzero(along <= 0)
    if len(r) == 0 or r[0] == 0:
        return float(0.5 * (d[b] + d[second[0]]))
    j = b + int(r[0])
    f = along[r[0] - 1] / (along[r[0] - 1] - along[r[0]])
    return float(d[j - 1] + f * (d[j] - d[j - 1]))


@dataclass(frozen=True)
class _Apex:
    """Where a stretch's curvature peaks, on its finest profile: arc m (the middle of the
    part over half the peak), peak 1/m, sigma 1/m (the profile's at the peak), span m (the
    length of the part over half the peak)."""

    arc: float
    peak: float
    sigma: float
    span: float


def _apexes(
    profile: CurvatureProfile,
    track: AxisTrack,
    spec: ImuSpec,
    stretches: list[tuple[int, int]],
    floor: float,
) -> list[_Apex | None]:
    """The apex of each stretch a..b (rows of profile), on a profile whose window is a quarter
    of the stretch over half the peak, refined until that stretch stops shrinking (a short
    bend is not averaged wider), at most 4 times; None for a stretch shorter than 3 points of
    its profile. The profiles of every stretch of a round are one call of windowed_curvature
    (a window per point): a call per stretch would be mostly numpy's overhead."""
    step = float(profile.distance[1] - profile.distance[0])
    half_w = 0.5 * profile.window
    lo, hi, width = [], [], []
    for a, b in stretches:
        peak = float(np.max(profile.total[a : b + 1]))
        over = np.flatnonzero(profile.total[a : b + 1] >= 0.5 * peak) + a
        half_len = float(profile.distance[over[-1]] - profile.distance[over[0]]) + step
        lo.append(float(track.arc_at(np.array([profile.distance[a]]))[0]) - half_w)
        hi.append(float(track.arc_at(np.array([profile.distance[b]]))[0]) + half_w)
        width.append(max(0.25 * half_len, floor))
    found: list[_Apex | None] = [None] * len(stretches)
    active = list(range(len(stretches)))
    for _ in range(4):
        grids = {i: np.arange(lo[i], hi[i], min(0.25 * width[i], APEX_STEP_M)) for i in active}
        for i in active:
            if len(grids[i]) < 3:
                found[i] = None
        active = [i for i in active if len(grids[i]) >= 3]
        if not active:
            break
        arc = np.concatenate([grids[i] for i in active])
        window = np.concatenate([np.full(len(grids[i]), width[i]) for i in active])
        fine = windowed_curvature(track, arc, window, spec)
        cuts = np.cumsum([len(grids[i]) for i in active])[:-1]
        narrowing = []
        for i, g, total, sigma in zip(active, np.split(arc, cuts), np.split(fine["total"], cuts),
                                      np.split(fine["sigma"], cuts), strict=True):  # fmt: skip
            k_peak = float(np.max(total))
            near = np.flatnonzero(total >= 0.5 * k_peak)
            span = float(g[near[-1]] - g[near[0]]) + float(g[1] - g[0])
            found[i] = _Apex(arc=float(0.5 * (g[near[0]] + g[near[-1]])), peak=k_peak,
                             sigma=float(sigma[int(np.argmax(total))]), span=span)  # fmt: skip
            narrower = max(0.25 * span, floor)
            if narrower < 0.9 * width[i]:
                width[i] = narrower
                narrowing.append(i)
        active = narrowing
    return found


def _measure(
    profile: CurvatureProfile,
    track: AxisTrack,
    spec: ImuSpec,
    a: int,
    b: int,
    ends: tuple[float, float],
    apex: _Apex,
    outer_diameter: float,
    class_limits: tuple[float, float, float],
    floor: float,
) -> PipeBend:
    """The bend of stretch a..b (rows of profile) between the chainages ``ends`` (m) with its
    ``apex`` (:func:`_apexes`); floor: the shortest arc the track resolves, m (one pass over the
    whole track, not one a bend)."""
    (ax0, ax1), (t0, t1) = track.at_arc(track.arc_at(np.array(ends)))
    angle = float(np.arccos(np.clip(ax0 @ ax1, -1.0, 1.0)))
    step = float(profile.distance[1] - profile.distance[0])
    # the rows within ends (the profile's chainage grid rises): a slice, not a mask of all
    span = slice(int(np.searchsorted(profile.distance, ends[0], "left")),
                 int(np.searchsorted(profile.distance, ends[1], "right")))  # fmt: skip
    vert = float(np.sum(profile.vertical[span]) * step)
    horiz = float(np.sum(profile.horizontal[span]) * step)
    apex_arc = apex.arc
    radius = 1.0 / max(apex.peak, 1e-12)
    sigma_radius = radius**2 * apex.sigma
    resolved = apex.span >= 3.0 * floor
    if not resolved:  # shorter than the track resolves: the radius is at most this
        sigma_radius = max(sigma_radius, radius)
    (apex_axis,), (apex_t,) = track.at_arc(np.array([apex_arc]))
    lat, lon, alt = (float(x[0]) for x in track.position_at(np.array([apex_arc])))
    pitch = math.asin(max(-1.0, min(1.0, float(apex_axis[2]))))
    azimuth = math.atan2(float(apex_axis[0]), float(apex_axis[1]))
    quat = quat_from_euler(0.0, pitch, azimuth).reshape(4)
    radius_d = radius / outer_diameter
    # a bend shorter than the rows' spacing is over the threshold at one row or two, and its
    # apex, found on the finer grid, may lie beyond them: its curvature is over the threshold
    # there too, so the bend reaches it (start <= apex <= end)
    apex_m = float(track.distance_at(np.array([apex_arc]))[0])
    return PipeBend(
        number=0,
        start_m=min(float(profile.distance[a]), apex_m),
        apex_m=apex_m,
        end_m=max(float(profile.distance[b]), apex_m),
        lat=lat,
        lon=lon,
        alt=alt,
        angle=angle,
        sigma_angle=float(relative_angle_sigma(spec, np.array([t1 - t0]), np.array([angle]))[0]),
        radius=radius,
        sigma_radius=sigma_radius,
        radius_d=radius_d,
        plane=math.atan2(horiz, vert) % (2.0 * math.pi),
        direction=bend_direction(vert, horiz),
        kind=bend_class(radius_d, class_limits),
        apex_t=float(apex_t),
        apex_quat_nb=tuple(float(x) for x in quat),  # type: ignore[arg-type]
        radius_resolved=resolved,
        sigma_h=float(track.sigma_at(np.array([apex_arc]))[0][0]),
        sigma_v=float(track.sigma_at(np.array([apex_arc]))[1][0]),
    )
