"""Markers stamped on another clock than the bag's: the offset measured, and taken out.

Above-ground markers log their passages on a clock of their own, and a marker file made from
them can be seconds or hours off the bag's: GPS time is 18 s ahead of UTC, a box set to local
time is whole hours off. Every passage then puts its survey where the pig was some metres or
kilometres away, the smoother cannot fit them, and the run fails with the IMU or the wheel
blamed (the sample's markers 18 s late: the path came out 2.9e17 m long, "check imu_grade").

Measured where the markers disagree with the run, or lie outside its data (the pipeline asks
only then): the run is dead-reckoned from its first epoch (the filter in ``dr`` mode: the IMU
and the wheel, no marker but a start), and for every offset that puts markers in the data,
``STEP_S`` apart and then ``FINE_S`` about the best, the markers' surveys are fitted to the
dead-reckoned positions at their passages less the offset, ``WINDOW`` markers in a row at a
time, by a rotation about the vertical, a scale and a shift (the heading, the wheel's scale and
the start, which the dead reckoning does not know, nor keeps over a long run). It starts on
the bearing of the first two markers' surveys and is run again on the heading each fit finds
while the fit improves, up to ``HEADING_PASSES`` times (a gyro that senses the Earth's rate
has it taken out in the wrong axes while the heading is off). The offset whose fit leaves the
smallest misfit, with as many markers fitted as any offset gives and three or more, is the
clock's; within ``SNAP_S`` of an offset clocks are known to be apart by (``KNOWN``: GPS time's
18 s against UTC, whole quarter hours of a time zone) it is that one. It is taken out where
it is a known one whose fit's misfit is at most ``KNOWN_IMPROVEMENT`` of the stamps' own (the
pipeline keeps the re-timed run only where its markers then agree with it). Another is only
named (``MIN_S`` or more, a misfit at most ``IMPROVEMENT`` of the stamps' own): the dead
reckoning puts it 0.1-1 s off (a 40 s offset: 38.95 to 40.14 s on three runs), and markers
re-timed that far off are fitted anyway, confidently wrong (the sample: 0.54 m off, 15 %
inside 3 sigma).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.smooth.centreline import forward_trajectory
from pipe_nav_core.smooth.forward import run_forward
from pipe_nav_core.types import Marker, SensorLog, markers_sorted

STEP_S = 0.5  # s, the coarse search's step
BATCH = 4096  # offsets fitted at once
WINDOW = 6  # markers in a row fitted on their own
FINE_S = 0.05  # s, the fine search's step about the coarse best (over +-2 coarse steps)
IMPROVEMENT = 0.6  # an offset's misfit against the stamps' own, at most, to be named
KNOWN_IMPROVEMENT = 0.9  # and a known one's, to be taken out (the smoothing then checks it)
MIN_S = 1.0  # s: an offset named (where not taken out) from this size
MIN_MARKERS = 3  # markers a fit needs (a rotation, a scale and a shift leave 2 x 3 - 4)
HEADING_PASSES = 5  # dead reckonings at most, each on the heading the one before fitted
SETTLED_RAD = 1e-3  # rad: a fit that turns the track less has its heading
SETTLED_SHARE = 0.95  # and a pass whose misfit is over this share of the one before
SNAP_S = 3.0  # s: an offset found this close to one of KNOWN is that one
# offsets that clocks are known to be apart by (s): GPS time ahead of UTC (18 s since 2017),
# whole quarter hours (a box on local time), and the two together
KNOWN = {18.0: "GPS time against UTC"}
KNOWN |= {900.0 * k: "a time zone's" for k in range(1, 57)}
KNOWN |= {900.0 * k + d: "a time zone's and GPS time against UTC" for k in range(1, 57)
          for d in (-18.0, 18.0)}  # fmt: skip

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MarkerClock:
    """The markers' stamps minus the bag's clock for the same passage (s; positive: the
    markers' are late), the fits' misfit (m rms, horizontal and vertical) at that offset and at
    the stamps as they are (inf where fewer than MIN_MARKERS of them fall in the data), and how
    many markers each fit had; ``retime``: it is to be taken out."""

    seconds: float
    misfit: float
    misfit_as_stamped: float
    markers: int
    markers_as_stamped: int
    retime: bool

    @property
    def named(self) -> bool:
        """Whether it is to be said: taken out, or an offset the markers fit far better."""
        return self.retime or (
            abs(self.seconds) >= MIN_S and self.misfit <= IMPROVEMENT * self.misfit_as_stamped
        )

    def describe(self, done: str = "re-timed to the bag's clock") -> str:
        """One line for people; ``done``: what was done about it."""
        way = "later" if self.seconds > 0 else "earlier"
        are = "are" if self.retime else "may be"
        stamped = (f"{self.misfit_as_stamped:.1f} m" if math.isfinite(self.misfit_as_stamped)
                   else f"{self.markers_as_stamped} of them in the data")  # fmt: skip
        known = KNOWN.get(abs(round(self.seconds, 3)), "")
        return (
            f"marker clock: the markers' passage times {are} {abs(self.seconds):.1f} s {way} "
            f"than the bag's clock{f' ({known})' if known else ''} (the dead-reckoned run "
            f"fits {self.markers} of their surveys to {self.misfit:.1f} m there, as stamped "
            f"{stamped}): {done}"
        )


def measure(log: SensorLog, markers: list[Marker], config: NavConfig) -> MarkerClock | None:
    """The offset of ``markers``' passage times (all of them, those outside the data too)
    from ``log``'s clock (module doc), or None where it cannot be measured (fewer than
    MIN_MARKERS markers, no dead reckoning)."""
    ms = [m for m in markers_sorted(markers) if math.isfinite(m.t)]
    if len(ms) < MIN_MARKERS or len(log.imu.t) < 10:
        return None
    o = ms[0]
    surveys = np.array([np.asarray(geodetic_to_enu(m.lat, m.lon, m.alt, o.lat, o.lon, o.alt),
                                   dtype=np.float64).reshape(3) for m in ms])  # fmt: skip
    stamps = np.array([m.t for m in ms])
    east, north = surveys[1, :2] - surveys[0, :2]
    found, azimuth = None, math.atan2(east, north)  # the bearing of the first two markers
    for _ in range(HEADING_PASSES):  # again on the heading each fit finds: where the heading
        # is far off, a gyro that senses the Earth's rate has it taken out in the wrong axes
        # and the track bends (the 3 km tactical line started north: 80 m off its markers)
        track = _dead_reckoned(log, o, config, azimuth)
        if track is None:
            return found
        clock, turn = _search(*track, stamps, surveys)
        if clock is None:
            return found
        if found is not None and clock.misfit >= SETTLED_SHARE * found.misfit:
            found = clock if clock.misfit < found.misfit else found
            break  # hardly better for the fit's heading (a gyro's drift, not the start's)
        found = clock
        azimuth = float(np.mod(azimuth - turn, 2.0 * math.pi))
        if abs(turn) < SETTLED_RAD:
            break
    return found


def _search(t: Array, enu: Array, stamps: Array, surveys: Array
            ) -> tuple[MarkerClock | None, float]:  # fmt: skip
    """The offset whose fit of ``surveys`` (N, 3) m ENU to the track (``t`` s, ``enu`` m)
    at ``stamps`` (N,) s less it is best (module doc), and that fit's rotation (rad,
    counter-clockwise seen from above)."""
    # every offset that puts a marker in the data
    coarse = np.arange(stamps[0] - t[-1], stamps[-1] - t[0] + STEP_S, STEP_S)
    misfit, count, _ = _fits(t, enu, stamps, surveys, coarse)
    at_zero, n_zero, _ = _fits(t, enu, stamps, surveys, np.zeros(1))
    most = max(MIN_MARKERS, int(count.max()))
    usable = count >= most
    if not usable.any():
        return None, 0.0
    best = float(coarse[np.flatnonzero(usable)[np.argmin(misfit[usable])]])
    fine = best + np.arange(-2 * STEP_S, 2 * STEP_S + FINE_S / 2, FINE_S)
    near = [v for v in KNOWN if abs(abs(best) - v) <= SNAP_S + 2 * STEP_S]
    # a clock known to be that far off, where it fits as well as the dead reckoning's nearest
    fine = np.r_[fine, [math.copysign(v, best) for v in near]]
    f_misfit, f_count, f_turn = _fits(t, enu, stamps, surveys, fine)
    f_usable = f_count >= most
    k = int(np.flatnonzero(f_usable)[np.argmin(f_misfit[f_usable])])
    known = [i for i in range(len(fine) - len(near), len(fine))
             if f_usable[i] and abs(fine[i] - fine[k]) <= SNAP_S]  # fmt: skip
    if known:
        k = min(known, key=lambda i: abs(fine[i] - fine[k]))
    seconds, low = float(fine[k]), float(f_misfit[k])
    retime = bool(known) and low <= KNOWN_IMPROVEMENT * float(at_zero[0])
    clock = MarkerClock(seconds=seconds, misfit=low, misfit_as_stamped=float(at_zero[0]),
                        markers=int(f_count[k]), markers_as_stamped=int(n_zero[0]),
                        retime=bool(retime))  # fmt: skip
    return clock, float(f_turn[k])


def retimed(markers: list[Marker], clock: MarkerClock) -> list[Marker]:
    """``markers`` with the offset taken out of their passage times."""
    return [replace(m, t=m.t - clock.seconds) for m in markers]


def _dead_reckoned(
    log: SensorLog, first: Marker, config: NavConfig, azimuth: float
) -> tuple[Array, Array] | None:
    """The wheel's dead reckoning (the filter in ``dr`` mode): its positions (K, 3) m ENU
    about ``first``'s survey at its epochs (K,) s, started at the first IMU sample on
    ``azimuth`` (rad, clockwise from north), without a marker to aid it."""
    start = replace(first, t=float(log.imu.t[0]))  # where it starts: a shift the fit takes out
    free = replace(config, mode="dr", heading_source="fixed", initial_azimuth=azimuth)
    try:
        nav = run_forward(replace(log, markers=[start]), free)
    except ValueError:
        return None
    if nav.recording is None:
        return None
    tr = forward_trajectory(nav.recording)
    enu = np.asarray(geodetic_to_enu(tr.lat, tr.lon, tr.h, first.lat, first.lon, first.alt),
                     dtype=np.float64).reshape(-1, 3)  # fmt: skip
    ok = np.isfinite(enu).all(axis=1) & np.isfinite(tr.t)
    if ok.sum() < 2:
        return None
    return np.asarray(tr.t, dtype=np.float64)[ok], enu[ok]


def _fits(t: Array, enu: Array, stamps: Array, surveys: Array, offsets: Array
          ) -> tuple[Array, Array, Array]:  # fmt: skip
    """Per offset: the misfit (m, rms per degree of freedom) of the surveys (N, 3) m ENU
    against the dead-reckoned positions at the stamps (N,) s less the offset, each WINDOW
    markers in a row fitted on their own (over a long run the dead reckoning drifts further
    than one fit can take out: 37 m over 100 km), over the markers then inside the data; the
    number of markers fitted (windows with fewer than MIN_MARKERS inside are not; inf misfit
    with none); and the first window's rotation (rad, counter-clockwise seen from above). In
    pieces of BATCH offsets (a 100 km run is tried at 2e5 offsets)."""
    cuts = list(range(0, len(stamps), WINDOW))
    if len(cuts) > 1 and len(stamps) - cuts[-1] < MIN_MARKERS:
        cuts.pop()  # the last few join the window before
    groups = [slice(a, b) for a, b in zip(cuts, [*cuts[1:], len(stamps)], strict=True)]
    out = []
    for a in range(0, max(len(offsets), 1), BATCH):
        o = offsets[a : a + BATCH]
        ssr, dof, n = np.zeros(len(o)), np.zeros(len(o)), np.zeros(len(o))
        turn = np.zeros(len(o))
        for k, g in enumerate(groups):
            g_ssr, g_n, g_turn = _fit_of(t, enu, stamps[g], surveys[g], o)
            ok = g_n >= MIN_MARKERS
            ssr += np.where(ok, g_ssr, 0.0)
            dof += np.where(ok, 3.0 * g_n - 5.0, 0.0)  # 2 n horizontal less 4, n vertical less 1
            n += np.where(ok, g_n, 0.0)
            if k == 0:
                turn = g_turn
        misfit = np.where(dof > 0, np.sqrt(np.maximum(ssr, 0.0) / np.maximum(dof, 1.0)), np.inf)
        out.append((misfit, n, turn))
    return tuple(np.concatenate(x) for x in zip(*out, strict=True))  # type: ignore[return-value]


def _fit_of(t: Array, enu: Array, stamps: Array, surveys: Array, offsets: Array
            ) -> tuple[Array, Array, Array]:  # fmt: skip
    """Per offset: the residual sum of squares (m^2) of the surveys against the dead-reckoned
    positions at the stamps less the offset, after the best rotation about the vertical,
    scale and shift (horizontal) and shift (vertical), over the markers then inside the data;
    their number; and the fit's rotation (rad, counter-clockwise seen from above)."""
    when = stamps[None, :] - offsets[:, None]  # (O, N)
    inside = (when >= t[0]) & (when <= t[-1])
    w = inside.astype(np.float64)
    n = w.sum(axis=1)
    at = np.stack([np.interp(when, t, enu[:, k]) for k in range(3)], axis=-1)  # (O, N, 3)
    safe = np.maximum(n, 1.0)[:, None]
    p = at[..., :2] - (np.sum(at[..., :2] * w[..., None], axis=1) / safe)[:, None, :]
    q = (
        surveys[None, :, :2]
        - (np.sum(surveys[None, :, :2] * w[..., None], axis=1) / safe)[:, None, :]
    )
    p *= w[..., None]
    q = q * w[..., None]
    # the similarity that takes p onto q (complex least squares: q = z p)
    dot = np.sum(p[..., 0] * q[..., 0] + p[..., 1] * q[..., 1], axis=1)
    cross = np.sum(p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0], axis=1)
    pp = np.maximum(np.sum(p**2, axis=(1, 2)), 1e-12)
    horiz = np.sum(q**2, axis=(1, 2)) - (dot**2 + cross**2) / pp
    dz = (surveys[None, :, 2] - at[..., 2]) * w
    vert = np.sum(dz**2, axis=1) - np.sum(dz, axis=1) ** 2 / safe[:, 0]
    return horiz + vert, n, np.arctan2(cross, dot)


__all__ = ["MarkerClock", "measure", "retimed"]
