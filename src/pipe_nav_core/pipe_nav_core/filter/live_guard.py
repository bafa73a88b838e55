"""The online engine behind the checks the live IMU stream needs (ekf_node, ``pipe-nav replay``).

Offline, the whole log is repaired before filtering (imu_faults, gaps, odometer_faults,
segments). Live, each IMU sample is checked as it comes, in its own stamp order:

- a **shock** (specific force over ``imu_faults.MAX_ACCEL`` from gravity, a rate over
  ``imu_faults.MAX_RATE``; and what comes within twice ``imu_faults.MARGIN_S`` of one, as
  offline) or a **saturated** reading (an axis repeating one value at least
  ``imu_faults.MIN_FLAT`` times at a magnitude no pig reaches in normal running: 2 g, 5 rad/s)
  is dropped;
- a **short hole** (over 1.5 sample periods, under a data gap) is filled by interpolating the
  samples either side before the next one goes in (the filter cannot integrate across it),
  when those agree (``QUIET_TURN``, ``QUIET_PUSH``); in a turn or a surge it is a data gap;
- a **hole at rest** (longer, but the odometer stood still across it and the samples either
  side agree: gaps.fill_holes_at_rest) is filled with the mean of the gaps.REST_WINDOW_S of
  samples before it (``imu_fault_filled_at_rest``): standing still, the IMU reads the same
  across it, and one sample's noise held for seconds tilts the filter (a 5 s shock on the
  3 km tactical line: 0.04 deg, the ZUPTs then rejected and the pig 7 m off at rest);
- any other **data gap** (the IMU silent for longer: a lost stretch, or a clock step) leaves the
  filter's attitude unknown: from then on the solution is **lost**: the engine gets no more
  input, its estimates after the loss are withheld, and the diagnostics say since when and
  why (``lost_since``, ``lost_reason``).

An **odometer reading** jumping over ``ODO_SPIKE_M`` from the last one at a speed no pig
reaches (``MAX_ODO_SPEED``, three times its own speed field) is dropped
(``odometer_fault_spike``).

A **marker** whose survey lies beyond ``MARKER_BOUND`` (chi-square, 3 dof) of the latest
estimate carried to its passage (the live filter cannot leave one out afterwards as the
smoother does) is dropped and named (``marker_outliers``, ``marker_fault_outlier``).

With the heading from the markers, the filter starts on the bearing between the first two
markers and re-anchors at the second by rotating its state about the first (engine). When that
rotation is large, everything it estimated on the way is wrong in a way the rotation does not
undo (the Earth rate compensated about the wrong axes: on a 3 km tactical line 75 degrees off,
the heading then drifted 15 mrad in 100 s, and the next markers looked like outliers). So at
the re-anchoring the guard finds the initial heading as the smoother does
(smooth.heading.anchored_config: dead reckoning to the second marker, secant) and **runs the filter
again** from the alignment over the inputs it kept, with that heading, leaving out the
readings of a stuck or spiking wheel found in them as offline (``odometer_fault_<kind>``); the
estimates already published stay, the later ones come from the new run (``heading_rerun``).
The inputs are kept only until then.

At the same moment the inputs kept show whether the **IMU's clock** is offset from the
odometer's (faults.clock_offset, measured at the pig's starts and stops as offline): if it is,
the filter runs again from the alignment with the IMU and the magnetometer re-timed, and so is
every later sample of theirs (``imu_clock_retimed``); an IMU later than the odometer by more
than the reorder window (minus ``CLOCK_MARGIN_S``) lets go of its samples too late to be
re-timed, and the solution is lost instead. Either way ``imu_clock`` in the diagnostics says
what was found.

A filter aligned before any marker (the first one late, or on another clock) has no position
until a marker places it: its estimates until then are withheld (``withheld_unpositioned``).
An estimate with a value or a variance not finite, or a horizontal sigma over
``DIVERGED_SIGMA_M``, is no solution: the solution is lost from the estimate before it
(``diverged``), and said so, rather than published.

Each IMU fault is counted in the diagnostics as ``imu_fault_<kind>``. Times s, rates rad/s,
forces m/s^2.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from pipe_nav_core.faults import clock_offset
from pipe_nav_core.faults.gaps import (
    MIN_GAP_S,
    REST_MOVED_M,
    REST_SPEED,
    REST_WINDOW_S,
    same_at_rest,
)
from pipe_nav_core.faults.imu import MARGIN_S, MAX_ACCEL, MAX_RATE, MIN_FLAT
from pipe_nav_core.faults.odometer import find_odometer_faults, without_faults
from pipe_nav_core.filter.estimates import NavEstimate
from pipe_nav_core.filter.ingest import mount_rotation
from pipe_nav_core.filter.kalman import chi2_threshold
from pipe_nav_core.filter.navigator import Navigator
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.types import ImuSamples, MagSamples, Marker, OdometerSamples, SensorLog

SATURATED_ACCEL = 19.6  # m/s^2 (2 g): an axis pinned at this or more is saturated
SATURATED_RATE = 5.0  # rad/s
GRAVITY = 9.81  # m/s^2, the reference of the shock test
QUIET_TURN = 1e-3  # rad: a hole is filled only if the rates either side differ by less ...
QUIET_PUSH = 0.05  # m/s: ... and the forces too (else the solution is lost)
# m: a horizontal sigma over this is no solution (nothing published before the first marker
# has more than some 1.4 km): the engine is lost, and says so, rather than publishing it
DIVERGED_SIGMA_M = 1e5
MARKER_BOUND = chi2_threshold(1.0 - 1e-6, 3)  # a marker this far off the estimate is dropped
RECENT_SAMPLES = 2048  # IMU samples kept for a fill at rest (REST_WINDOW_S up to 4 kHz)
MAX_ODO_SPEED = 10.0  # m/s: an odometer reading implying more since the last is a spike ...
ODO_SPIKE_M = 0.5  # m: ... when it jumps by more than this
CLOCK_MARGIN_S = 0.1  # s of the reorder window a re-timed IMU sample must still have


class GuardedNavigator(Navigator):
    """A Navigator whose IMU input is checked first (see the module)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self._last: tuple[float, tuple[float, ...], tuple[float, ...]] | None = None
        self._recent: deque[tuple[float, tuple[float, ...], tuple[float, ...]]] = deque(
            maxlen=RECENT_SAMPLES
        )  # the last samples taken, for a fill at rest
        self._period: float | None = None
        self._repeat = [0] * 6  # per axis (gyro, accel): the same high reading repeated
        self.lost_since: float | None = None
        self.lost_reason = ""
        self._latest: NavEstimate | None = None
        self._last_odo: tuple[float, float] | None = None
        self._last_odo_speed = math.inf
        self._shock_t = -math.inf  # s: the last shock reading
        self._odo_at_last_imu: tuple[float, float] | None = None
        self.marker_outliers: list[str] = []
        # the inputs given to the engine, until the heading is anchored (then None)
        self._kept: list[tuple[float, str, object]] | None = (
            [] if self.cfg.heading_source == "markers" and self.reference is None else None
        )
        self._published = -math.inf  # s: the last estimate poll returned
        self._clock: clock_offset.ClockOffset | None = None  # the IMU's, once re-timed
        self._clock_note = ""  # what the inputs kept said of the IMU's clock

    def push_imu(self, t: float, gyro: Sequence[float], accel: Sequence[float]) -> None:
        if self.lost_since is not None:
            self._counts["ignored_lost"] += 1
            return
        if self._clock is not None:
            t -= float(self._clock.at(t))
        g = gx, gy, gz = (float(gyro[0]), float(gyro[1]), float(gyro[2]))
        a = ax, ay, az = (float(accel[0]), float(accel[1]), float(accel[2]))
        if not math.isfinite(t + gx + gy + gz + ax + ay + az) and not all(
            map(math.isfinite, (t, *g, *a))
        ):
            super().push_imu(t, g, a)  # counted and dropped there
            return
        rate = math.hypot(gx, gy, gz)
        force = math.hypot(ax, ay, az)
        if abs(force - GRAVITY) > MAX_ACCEL or rate > MAX_RATE:
            self._counts["imu_fault_shock"] += 1
            self._shock_t = t
            return
        if t - self._shock_t <= 2.0 * MARGIN_S:  # amid a shock's readings: part of the shock
            self._counts["imu_fault_shock"] += 1
            return
        # an axis at a saturating magnitude needs a norm at least that large
        if (rate >= SATURATED_RATE or force >= SATURATED_ACCEL or any(self._repeat)) and (
            self._saturated(g, a)
        ):
            self._counts["imu_fault_saturated"] += 1
            return
        last = self._last
        if last is not None and t > last[0]:
            dt = t - last[0]
            period = self._period or dt
            if dt > max(MIN_GAP_S, 50.0 * period):
                if self._stood_still(last, (t, g, a)):
                    rest = self._rest_before(last[0])
                    self._fill((last[0], *rest), (t, *rest), period)
                    self._counts["imu_fault_filled_at_rest"] += 1
                else:
                    why = (f"the IMU was silent for {dt:.1f} s (a data gap or a clock step): "
                           "the attitude is not known across it")  # fmt: skip
                    self._lose(last[0], why)
            elif dt > 1.5 * period:
                turn = max(abs(x - y) for x, y in zip(g, last[1], strict=True)) * dt
                push = max(abs(x - y) for x, y in zip(a, last[2], strict=True)) * dt
                if turn <= QUIET_TURN and push <= QUIET_PUSH:
                    self._fill(last, (t, g, a), period)
                else:
                    why = (f"{dt:.2f} s of IMU samples missing while the pig turned or "
                           "accelerated: the attitude is not known across it")  # fmt: skip
                    self._lose(last[0], why)
            else:
                self._period = dt if self._period is None else 0.99 * self._period + 0.01 * dt
        self._last = (t, g, a)
        self._recent.append(self._last)
        self._odo_at_last_imu = self._last_odo
        self._push(t, "imu", (gx, gy, gz, ax, ay, az))  # Inbox.imu_sample's, checked above

    def _rest_before(self, t0: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The mean rate and specific force of the samples taken in the REST_WINDOW_S up to
        t0 (s)."""
        window = [(g, a) for t, g, a in self._recent if t > t0 - REST_WINDOW_S]
        g, a = np.mean([w[0] for w in window], axis=0), np.mean([w[1] for w in window], axis=0)
        return tuple(map(float, g)), tuple(map(float, a))

    def _stood_still(self, last: tuple, nxt: tuple) -> bool:
        """Whether the pig stood still across an IMU hole from sample last to nxt: the
        odometer read the same (gaps.REST_MOVED_M) at a standstill (gaps.REST_SPEED) before
        and after, and the gravity direction and the rates agree (five times gaps' bounds on
        window means: these are single samples)."""
        before, now = self._odo_at_last_imu, self._last_odo
        if before is None or now is None or now[0] < nxt[0] - 1.0:
            return False
        if abs(now[1] - before[1]) >= REST_MOVED_M or self._last_odo_speed >= REST_SPEED:
            return False
        return same_at_rest(last[1], last[2], nxt[1], nxt[2], slack=5.0)

    def push_odometer(self, t: float, distance: float, speed: float) -> None:
        if self.lost_since is not None:
            return
        last = self._last_odo
        if last is not None and t > last[0] and math.isfinite(distance):
            implied = abs(distance - last[1]) / (t - last[0])
            if (
                implied > max(MAX_ODO_SPEED, 3.0 * abs(speed) + 1.0)
                and abs(distance - last[1]) > ODO_SPIKE_M
            ):
                self._counts["odometer_fault_spike"] += 1
                return
        if math.isfinite(t) and math.isfinite(distance):
            self._last_odo = (t, distance)
            self._last_odo_speed = abs(speed) if math.isfinite(speed) else math.inf
        super().push_odometer(t, distance, speed)

    def push_mag(self, t: float, field_t: Sequence[float]) -> None:
        if self.lost_since is None:
            if self._clock is not None:
                t -= float(self._clock.at(t))
            super().push_mag(t, field_t)

    def push_marker(self, marker: Marker) -> None:
        if self.lost_since is not None:
            return
        nis = self._marker_nis(marker)
        if nis > MARKER_BOUND:
            self._counts["marker_fault_outlier"] += 1
            self.marker_outliers.append(f"{marker.name} ({nis:.0f})")
            return
        super().push_marker(marker)

    def _marker_nis(self, marker: Marker) -> float:
        """The marker's normalized squared innovation against the latest estimate carried to
        its passage (position covariance + survey + passage time x speed); 0 when unknown."""
        e = self._latest
        if e is None or not 0.0 <= marker.t - e.t <= 2.0:
            return 0.0
        if self.datum is None or not self.anchor.anchored or len(self.inbox.markers_seen) < 2:
            return 0.0  # the datum and the heading come from the first markers: not tested
        vel = np.asarray(e.vel_n, dtype=np.float64)
        pos = geodetic_to_enu(e.lat, e.lon, e.h, marker.lat, marker.lon, marker.alt).reshape(3)
        r = pos + vel * (marker.t - e.t)
        cov = (
            np.asarray(e.cov_pose, dtype=np.float64)[:3, :3]
            + np.diag(np.square(np.asarray(marker.sigma_enu, dtype=np.float64)))
            + self.cfg.marker_time_sigma**2 * np.outer(vel, vel)
        )
        return float(r @ np.linalg.solve(cov, r))

    def _saturated(self, g: tuple[float, ...], a: tuple[float, ...]) -> bool:
        """True while an axis repeats one high reading MIN_FLAT times or more."""
        repeat = self._repeat
        if max(map(abs, g)) < SATURATED_RATE and max(map(abs, a)) < SATURATED_ACCEL:
            if any(repeat):  # no axis high: every count ends
                self._repeat = [0] * 6
            return False
        values = (*g, *a)
        prev = (*self._last[1], *self._last[2]) if self._last is not None else None
        for i, v in enumerate(values):
            high = abs(v) >= (SATURATED_RATE if i < 3 else SATURATED_ACCEL)
            repeat[i] = repeat[i] + 1 if prev is not None and high and v == prev[i] else 0
        return max(repeat) >= MIN_FLAT - 1

    def _fill(self, last: tuple, nxt: tuple, period: float) -> None:
        t0, g0, a0 = last
        t1, g1, a1 = nxt
        n = int(round((t1 - t0) / period)) - 1
        for k in range(1, n + 1):
            f = k / (n + 1)
            super().push_imu(t0 + f * (t1 - t0), tuple(x + f * (y - x) for x, y in zip(g0, g1)),
                             tuple(x + f * (y - x) for x, y in zip(a0, a1)))  # fmt: skip
        self._counts["imu_fault_filled"] += n

    def _lose(self, t: float, why: str, count: str = "imu_fault_data_gap") -> None:
        """The solution lost from ``t`` (s) for ``why`` (the first loss stays), counted as
        ``count`` in the diagnostics."""
        self._counts[count] += 1
        if self.lost_since is None:
            self.lost_since, self.lost_reason = t, why

    def _push(self, t: float, kind: str, payload: object) -> None:
        if self._kept is not None:
            self._kept.append((t, kind, payload))
        super()._push(t, kind, payload)

    def poll(self) -> list[NavEstimate]:  # Navigator.finish returns it too
        out = super().poll()
        if out or self._rerun_due:
            return self._published_only(out)
        return out  # the common case: nothing new (called after every sample)

    @property
    def _rerun_due(self) -> bool:
        """Anchored with the inputs still kept: the re-run from the anchored heading is next."""
        return self._kept is not None and self.anchor.anchored

    def _published_only(self, out: list[NavEstimate]) -> list[NavEstimate]:
        if self._rerun_due:
            out = self._rerun(out)
        out = [e for e in out if e.t > self._published]
        if self.positioned_at > -math.inf:  # aligned before any marker: no position till one
            self._counts["withheld_unpositioned"] += sum(e.t < self.positioned_at for e in out)
            out = [e for e in out if e.t >= self.positioned_at]
        bad = next((k for k, e in enumerate(out) if _diverged(e)), None)
        if bad is not None and self.lost_since is None:
            self._lose(
                out[bad - 1].t if bad else self._published,
                f"the filter diverged at t = {out[bad].t:.3f} s (a state or sigma not finite, "
                f"or a horizontal sigma over {DIVERGED_SIGMA_M:.0f} m): its markers contradict "
                "the run beyond recovery (a marker clock?) or its IMU model does not fit",
                "diverged",
            )
            out = out[:bad]
        if out:
            self._latest = out[-1]
            self._published = out[-1].t
        if self.lost_since is None:
            return out
        kept = [e for e in out if e.t <= self.lost_since]
        self._counts["withheld_lost"] += len(out) - len(kept)
        return kept

    def _rerun(self, out: list[NavEstimate]) -> list[NavEstimate]:
        """Once anchored: the filter run again from the start with the initial heading found
        by smooth.heading.anchored_config (see the module), when the re-anchoring turned it; the
        estimates up to the anchoring's epoch (of out) are returned as they are, the later ones
        come from the new run (out can reach past the anchoring when a backlog released many
        epochs at once: which estimates come from which run does not depend on that)."""
        from pipe_nav_core.smooth.heading import anchored_config

        kept, self._kept = self._kept or [], None
        if len(self.inbox.markers_seen) < 2:
            return out
        second = sorted(m.t for m in self.inbox.markers_seen)[1]  # s, before reset() clears it
        log = _log_of(kept)
        clock = self._clock_of(log, second)
        if clock is not None:
            log = clock_offset.retimed(log, clock)
            kept = sorted(((t - float(clock.at(t)) if kind in ("imu", "mag") else t, kind, p)
                           for t, kind, p in kept), key=lambda x: x[0])  # fmt: skip
        elif self.reanchor_rad == 0.0 or self.lost_since is not None:
            return out
        # the wheel's faults so far, found as offline (odometer_faults) and left out of both
        log, faults = without_faults(log, find_odometer_faults(log))
        try:
            cfg = anchored_config(log, self.cfg, self)
        except ValueError:  # the dead reckoning found no solution in what was kept: go on
            self._counts["heading_rerun_failed"] += 1
            cfg = self.cfg if clock is not None else None
        if cfg is None or (cfg is self.cfg and clock is None):
            return out
        counts, declared = dict(self._counts), self.declared_imu_noise
        self.cfg = cfg
        self.reset()
        self.declared_imu_noise = declared
        self._clock = clock
        good = set(log.odometer.t.tolist())
        for t, kind, payload in kept:
            if kind != "odometer" or t in good:
                Navigator._push(self, t, kind, payload)
        for f in faults:
            counts[f"odometer_fault_{f.kind}"] = counts.get(f"odometer_fault_{f.kind}", 0) + 1
        for k, v in counts.items():  # the guard's counts and the first run's re-anchoring
            self._counts.setdefault(k, v)
        self._counts["heading_rerun"] += 1
        at = next((i for i, e in enumerate(out) if e.t >= second), len(out) - 1)
        out = out[: at + 1]  # up to the anchoring's epoch: the rest comes from the new run
        last = out[-1].t if out else self._published
        return out + [e for e in Navigator.poll(self) if e.t > last]

    def _clock_of(self, log: SensorLog, now: float) -> clock_offset.ClockOffset | None:
        """The IMU's clock offset the inputs kept show, when it is to be taken out live (see
        the module); noted for the diagnostics, and the solution lost where it cannot be."""
        found = clock_offset.measure(log, mount_rotation(self.cfg.imu_mount_rpy))
        if found is None or not found.named:
            return None
        self._clock_note = found.describe()
        if not found.retime:
            return None
        if max(found.first, found.last) > self.cfg.reorder_window_s - CLOCK_MARGIN_S:
            self._clock_note = found.describe(
                "more than the reorder window lets the live filter re-time (pipe-nav smooth "
                "re-times it)"
            )
            self._lose(now, self._clock_note, "imu_clock_lost")
            return None
        self._counts["imu_clock_retimed"] += 1
        return found

    def diagnostics(self) -> dict[str, int | float | str]:
        d = super().diagnostics()
        if self._clock_note:
            d["imu_clock"] = self._clock_note
        if self.marker_outliers:
            d["marker_outliers"] = ", ".join(self.marker_outliers)
        if self.lost_since is not None:
            d["state"] = "lost"
            d["lost_since"] = self.lost_since
            d["lost_reason"] = self.lost_reason
        return d


def _diverged(e: NavEstimate) -> bool:
    """Whether an estimate is no solution: a value or variance not finite, or a horizontal
    sigma over DIVERGED_SIGMA_M."""
    var = np.diagonal(e.cov_pose)
    values = np.r_[e.lat, e.lon, e.h, e.vel_n, e.quat_nb, var]
    return not (np.isfinite(values).all() and var[0] + var[1] <= DIVERGED_SIGMA_M**2)


def _log_of(kept: list[tuple[float, str, object]]) -> SensorLog:
    """The inputs kept (stamp s, kind, payload as Navigator._push takes them) as a log."""
    by: dict[str, list[tuple[float, object]]] = {"imu": [], "odometer": [], "mag": [], "marker": []}
    for t, kind, payload in sorted(kept, key=lambda x: x[0]):
        by[kind].append((t, payload))
    imu = np.array([[t, *p] for t, p in by["imu"]]).reshape(-1, 7)  # type: ignore[misc]
    odo = np.array([[t, *p] for t, p in by["odometer"]]).reshape(-1, 3)  # type: ignore[misc]
    mag = np.array([[t, *m] for t, m in by["mag"]]).reshape(-1, 4)  # type: ignore[misc]
    return SensorLog(
        ImuSamples(imu[:, 0], imu[:, 1:4], imu[:, 4:7]),
        OdometerSamples(odo[:, 0], odo[:, 1], odo[:, 2]),
        MagSamples(mag[:, 0], mag[:, 1:4]),
        [m for _t, m in by["marker"]],  # type: ignore[misc]
    )
