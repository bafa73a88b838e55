"""A run cut by data gaps, smoothed segment by segment and joined.

Across a gap the pig moved with nothing recorded, so no filter can carry its attitude over:
each segment between gaps is smoothed on its own, tied to the ground by its own markers. A
segment that starts at rest (the launch trap) is smoothed forward; one that ends at rest (the
receive trap) is smoothed in reversed time (smooth.logs.reverse_log, the Earth turning backwards),
aligning at its end; one with neither (between two gaps, the pig moving at both ends) cannot
be aligned, and one whose markers disagree with its solution is not trusted: both are left
unmapped, named. The
centreline then has no rows across the gaps; its chainage goes on across each gap by the
odometer distance in it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from pipe_nav_core.config import NavConfig
from pipe_nav_core.faults.gaps import TimeHole
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.io.centreline import concat
from pipe_nav_core.smooth.centreline import SmoothResult, arc_chainage
from pipe_nav_core.smooth.logs import reverse_log
from pipe_nav_core.types import SensorLog, Trajectory


@dataclass(frozen=True)
class Segment:
    """The data from t0 to t1 (s); how it was smoothed: ``forward``, ``reversed`` or
    ``unmapped`` (and why)."""

    t0: float
    t1: float
    how: str
    why: str = ""


def cut(log: SensorLog, t0: float, t1: float) -> SensorLog:
    """The samples and markers of ``log`` with t0 <= t <= t1 (s)."""

    def inside(t: np.ndarray) -> np.ndarray:
        return (t >= t0) & (t <= t1)

    return replace(samples_where(log, inside), markers=[x for x in log.markers
                                                        if t0 <= x.t <= t1])  # fmt: skip


def samples_where(log: SensorLog, keep: Callable[[np.ndarray], np.ndarray]) -> SensorLog:
    """The log with only the IMU, odometer and magnetometer samples whose stamps (s) ``keep``
    maps to True; the markers as they are."""
    o, m = log.odometer, log.mag
    ko, km = keep(o.t), keep(m.t)
    return replace(
        log,
        imu=log.imu.slice(keep(log.imu.t)),
        odometer=replace(o, t=o.t[ko], distance=o.distance[ko], speed=o.speed[ko]),
        mag=replace(m, t=m.t[km], field=m.field[km]),
    )


def at_rest(log: SensorLog, config: NavConfig, end: bool) -> bool:
    """Whether the odometer stands still over the static alignment span at the start (or end)."""
    o = log.odometer
    if len(o.t) < 2:
        return False
    span = config.static_alignment_s
    k = o.t >= o.t[-1] - span if end else o.t <= o.t[0] + span
    still = max(config.stop_speed_threshold, 0.01)
    return bool(np.ptp(o.distance[k]) < 0.01 and np.all(np.abs(o.speed[k]) < still))


def unreversed(traj: Trajectory) -> Trajectory:
    """A trajectory estimated in reversed time (t -> -t) back in forward time."""

    def flip(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else np.asarray(a)[::-1].copy()

    return Trajectory(t=-traj.t[::-1], lat=flip(traj.lat), lon=flip(traj.lon), h=flip(traj.h),
                      vel_n=-np.asarray(traj.vel_n)[::-1], quat_nb=flip(traj.quat_nb),
                      distance=flip(traj.distance), sigma_enu=flip(traj.sigma_enu),
                      sigma_att=flip(traj.sigma_att), cov_pose=flip(traj.cov_pose))  # fmt: skip


def smooth_segments(
    log: SensorLog,
    config: NavConfig,
    gaps: list[TimeHole],
    smooth: Callable[..., SmoothResult],
) -> tuple[SmoothResult, list[Segment]]:
    """Smooth each segment between ``gaps`` (see the module) and join them with ``smooth(log,
    reverse=False)`` (reverse: a log in reversed time); ValueError when no segment can be
    smoothed."""
    bounds = [-math.inf] + [x for g in gaps for x in (g.t_before, g.t_after)] + [math.inf]
    pieces: list[tuple[Segment, SmoothResult]] = []
    segments: list[Segment] = []
    for a, b in zip(bounds[::2], bounds[1::2], strict=True):
        part = cut(log, a, b)
        t0, t1 = (float(part.imu.t[0]), float(part.imu.t[-1])) if len(part.imu.t) else (a, b)
        if len([m for m in part.markers if math.isfinite(m.t)]) < 1 or len(part.imu.t) < 10:
            segments.append(Segment(t0, t1, "unmapped", "no marker in it"))
            continue
        if at_rest(part, config, end=False):
            res, how = smooth(part), "forward"
        elif at_rest(part, config, end=True):
            res, how = _reversed(smooth(reverse_log(part), reverse=True)), "reversed"
        else:
            segments.append(Segment(t0, t1, "unmapped", "the pig moves at both ends"))
            continue
        if res.summary.get("marker_disagreement"):
            segments.append(Segment(t0, t1, "unmapped", f"smoothed {how}, its "
                                    f"{res.summary['marker_disagreement']}"))  # fmt: skip
            continue
        seg = Segment(t0, t1, how)
        segments.append(seg)
        pieces.append((seg, res))
    if not pieces:
        raise ValueError("no segment between the data gaps can be smoothed (each needs a marker "
                         "and a start or end at rest)")  # fmt: skip
    return _joined(log, config, [p[1] for p in pieces]), segments


def _reversed(res: SmoothResult) -> SmoothResult:
    c = unreversed(res.centreline)
    c = replace(c, distance=arc_chainage(c.lat, c.lon, c.h, c.quat_nb))
    markers = sorted(res.markers, key=lambda m: m.t)
    markers = [replace(m, t=-m.t) for m in markers[::-1]]
    return replace(res, centreline=c, forward=unreversed(res.forward), markers=markers)


@dataclass(frozen=True)
class Bridge:
    """What the odometer says of the pipe between two mapped segments: it runs from the last
    row before (lat0, lon0 rad, alt0 m, t0 s) to the first row after (lat1, lon1, alt1, t1),
    ``length`` m long by the odometer (scale-calibrated), ``chord`` m apart in a straight line.
    A curve of length L between two points c apart lies in the ellipsoid they focus, within
    sqrt(L^2 - c^2) / 2 of the line; ``within`` (m) is that with L at 3 sigma of the odometer
    scale prior above (a wheel slipping in the gap is not known) and c at 3 sigma of the two
    ends' position below."""

    t0: float
    t1: float
    lat0: float
    lon0: float
    alt0: float
    lat1: float
    lon1: float
    alt1: float
    length: float
    chord: float
    within: float

    def describe(self) -> str:
        return (
            f"the pipe between t = {self.t0:.3f} and {self.t1:.3f} s is not mapped: "
            f"{self.length:.2f} m of it by the odometer, {self.chord:.2f} m end to end, so "
            f"within {self.within:.2f} m of the straight line between them"
        )


def _bridge(prev: Trajectory, nxt: Trajectory, length: float, scale_sigma: float) -> Bridge:
    a = (float(prev.lat[-1]), float(prev.lon[-1]), float(prev.h[-1]))
    b = (float(nxt.lat[0]), float(nxt.lon[0]), float(nxt.h[0]))
    chord = float(np.linalg.norm(geodetic_to_enu(*b, *a)))
    ends = sum(float(np.linalg.norm(x.sigma_enu[i])) for x, i in ((prev, -1), (nxt, 0))
               if x.sigma_enu is not None)  # fmt: skip
    longest = length * (1.0 + 3.0 * scale_sigma)
    shortest = max(chord - 3.0 * ends, 0.0)
    return Bridge(float(prev.t[-1]), float(nxt.t[0]), *a, *b, length, chord,
                  0.5 * math.sqrt(max(longest**2 - shortest**2, 0.0)))  # fmt: skip


def _joined(log: SensorLog, config: NavConfig, parts: list[SmoothResult]) -> SmoothResult:
    """One result from the segments' (in time order): centreline and forward estimates one
    after the other, the chainage going on across each gap by the odometer distance in it
    (scaled by the segment before's calibration); the summary's ``bridges`` say what the
    odometer bounds of the pipe across (:class:`Bridge`)."""
    odo = log.odometer
    centre: list[Trajectory] = []
    forward: list[Trajectory] = []
    bridges: list[Bridge] = []
    offset = 0.0
    for k, p in enumerate(parts):
        c = p.centreline
        if k:
            prev = centre[-1]
            across = float(np.interp(c.t[0], odo.t, odo.distance)
                           - np.interp(prev.t[-1], odo.t, odo.distance))  # fmt: skip
            across = max(across, 0.0) * float(parts[k - 1].summary.get("odometer_scale", 1.0))
            bridges.append(_bridge(prev, c, across, config.odometer_scale_sigma))
            offset = float(prev.distance[-1]) + across - float(c.distance[0])
        centre.append(replace(c, distance=c.distance + offset))
        forward.append(p.forward)
    first = parts[0]
    summary = dict(first.summary)
    for key in ("markers_used", "markers_rejected", "markers_total", "straight_pipe_updates",
                "section_direction_updates"):  # fmt: skip
        summary[key] = sum(int(p.summary.get(key, 0)) for p in parts)  # type: ignore[call-overload]
    summary["gentle_curves_m"] = sum(float(p.summary.get("gentle_curves_m", 0.0)) for p in parts)  # type: ignore[arg-type]
    for key in ("warnings", "marker_warnings", "marker_outliers"):
        summary[key] = [w for p in parts for w in p.summary.get(key, [])]  # type: ignore[attr-defined]
    for key in ("max_sigma_h_between_markers_m", "max_marker_residual_m"):
        summary[key] = max(float(p.summary.get(key, 0.0)) for p in parts)  # type: ignore[arg-type]
    # the passes of the segment that converged least (the quality verdict judges them)
    passes = [p.summary for p in parts if "converged" in p.summary]
    if passes:
        least = max(passes, key=lambda x: (not x["converged"], float(x["last_step_rad"])))  # type: ignore[arg-type]
        for key in ("converged", "passes_run", "last_step_m", "last_step_rad"):
            summary[key] = least[key]
    rejected: dict[str, int] = {}
    for p in parts:
        for name, n in (p.summary.get("rejected_updates") or {}).items():  # type: ignore[attr-defined]
            rejected[name] = rejected.get(name, 0) + int(n)
    summary["rejected_updates"] = rejected
    joined = concat(centre)
    summary["bridges"] = [vars(x) for x in bridges]
    summary["warnings"] = summary["warnings"] + [x.describe() for x in bridges]  # type: ignore[operator]
    summary["distance_m"] = float(joined.distance[-1])
    summary["duration_s"] = float(joined.t[-1] - joined.t[0])
    residuals = {name: r for p in parts for name, r in p.marker_residuals.items()}
    return SmoothResult(joined, concat(forward), first.datum, [m for p in parts for m in p.markers],
                        residuals, summary, first.config)  # fmt: skip
