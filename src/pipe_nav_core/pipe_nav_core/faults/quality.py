"""The quality verdict of a smoothed run: OK, DEGRADED (with its reasons) or FAILED.

A centreline is only worth its verdict: FAILED when the solution is physically absurd (an
odometer scale factor far from 1, position sigmas of kilometres or of a tenth of the run's
chainage: a filter that has lost its way, nothing finite), nothing tied it to the ground or
the smoothing passes were still moving it by much; DEGRADED when something the engineer must
know about happened (the IMU model did not fit, markers were rejected or left out, the heading
is not anchored, messages were skipped, the bag was cut short, the passes stopped short of
converging, the filter reached markers having lost the odometer); else OK. ``pipe-nav smooth``
prints it, writes it into the smoothed bag (MCAP metadata ``pipe_nav``) and, with
``--strict``, exits 3 unless OK.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from pipe_nav_core.types import OdometerSamples, Trajectory

OK, DEGRADED, FAILED = "OK", "DEGRADED", "FAILED"
SCALE_LIMITS = (0.8, 1.25)  # odometer scale factors outside: a wrong solution, not a wheel
MAX_SIGMA_H_M = 1000.0  # m, a horizontal sigma beyond which the centreline locates nothing
# a horizontal sigma beyond this share of the run's chainage span: the filter is lost (a
# diverged run reaches sigmas like the pipe's length; a sound one stays under 0.1 % of it)
LOST_SHARE, LOST_MIN_SPAN_M = 0.1, 10.0  # (a run shorter than the span is judged as that long)
# smoothing passes that stopped before converging (smooth.passes) leave the centreline off the
# optimum by about the next pass's step, second order in the last one: a last attitude step
# over this and the centreline is not known to its sigmas (a sound run's second pass moves
# the attitude by 0.03 to 7 mrad, its third by under 0.4; a diverged run's fifth by tens)
UNCONVERGED_RAD = 0.01


# a smoothed path longer than this many times the wheel's count, plus PATH_SLACK_M, is not the
# pipe: the filter lost its way (a wheel off by SCALE_LIMITS and slips stay far inside; the
# sample with its IMU's mount 90 deg off made a path of 6 km, the products' grid of it 24 GB)
PATH_FACTOR, PATH_SLACK_M = 2.0, 50.0


def lost_path(centreline: Trajectory, odometer: OdometerSamples) -> str:
    """Why the smoothed path is not the pipe (its length, m, beyond PATH_FACTOR times the
    odometer's count plus PATH_SLACK_M, or not finite), or '' where it may be."""
    if len(centreline.t) < 2 or len(odometer.t) < 2:
        return ""
    counted = float(np.ptp(odometer.distance))
    path = float(np.ptp(centreline.distance))
    if path <= PATH_FACTOR * counted + PATH_SLACK_M:  # (False for nan)
        return ""
    return (f"the smoothed path is {path:.4g} m long where the wheel counted {counted:.0f} m: "
            "not the pipe (the filter lost its way; check the IMU's mount, imu_mount_rpy, and "
            "its grade, imu_grade); no integrity products made of it")  # fmt: skip


@dataclass
class Verdict:
    """status: OK | DEGRADED | FAILED; reasons: one line each (empty when OK)."""

    status: str = OK
    reasons: list[str] = field(default_factory=list)

    def line(self) -> str:
        """``OK``, or ``DEGRADED: reason; reason``."""
        return self.status + (f": {'; '.join(self.reasons)}" if self.reasons else "")


def judge(
    summary: dict[str, object],
    centreline: Trajectory,
    warnings: Sequence[str] = (),
    failures: Sequence[str] = (),
) -> Verdict:
    """The verdict of a smoothing summary (smooth.centreline.summarize), its centreline, the
    warnings of reading the bag and of the model check, and faults known to spoil the answer."""
    failed: list[str] = list(failures)
    degraded: list[str] = []
    scale = float(summary.get("odometer_scale", 1.0))  # type: ignore[arg-type]
    if not (math.isfinite(scale) and SCALE_LIMITS[0] <= scale <= SCALE_LIMITS[1]):
        failed.append(
            f"odometer scale factor {scale:.3f} outside {SCALE_LIMITS[0]}-{SCALE_LIMITS[1]}"
        )
    c = centreline
    finite = bool(np.isfinite(c.lat).all() and np.isfinite(c.lon).all() and np.isfinite(c.h).all())
    if not finite or len(c.t) == 0:
        failed.append("the centreline has non-finite positions")
    if c.sigma_enu is not None and len(c.t):
        sig_h = np.hypot(c.sigma_enu[:, 0], c.sigma_enu[:, 1])
        worst = float(np.nanmax(sig_h)) if np.isfinite(sig_h).any() else math.inf
        span = float(np.ptp(c.distance)) if np.isfinite(c.distance).all() else math.inf
        lost = (": the filter lost its way (epochs too long for the run's motion: "
                "filter_rate_hz, smoother_rate_hz; or an IMU grade that does not fit)")  # fmt: skip
        if not worst <= MAX_SIGMA_H_M:
            failed.append(f"horizontal sigma up to {worst:.0f} m{lost}")
        elif worst > LOST_SHARE * max(span, LOST_MIN_SPAN_M):
            failed.append(
                f"horizontal sigma up to {worst:.1f} m over {span:.1f} m of chainage{lost}"
            )
    passes = int(summary.get("passes_run", 1))  # type: ignore[call-overload]
    if summary.get("converged") is False and passes >= 2:  # one pass: nothing to converge
        step = float(summary.get("last_step_rad", 0.0))  # type: ignore[arg-type]
        why = (f"the {passes} smoothing passes did not converge (the last moved the attitude "
               f"by {1e3 * step:.1f} mrad)")  # fmt: skip
        if not step <= UNCONVERGED_RAD:
            failed.append(f"{why}: the centreline is not known to its sigmas")
        else:
            degraded.append(f"{why}: more --iterations may help")
    if int(summary.get("markers_used", 0)) == 0:  # type: ignore[call-overload]
        failed.append("no marker was used: nothing ties the run to the ground")
    rejected = int(summary.get("markers_rejected", 0))  # type: ignore[call-overload]
    if rejected:
        degraded.append(f"{rejected} marker(s) rejected")
    lost = [str(m) for m in summary.get("markers_after_odometer_loss") or []]  # type: ignore[union-attr]
    if lost:
        more = f" and {len(lost) - 3} more" if len(lost) > 3 else ""
        degraded.append(
            f"the filter had lost the odometer (rejected most of its speed updates) before "
            f"marker(s) {', '.join(lost[:3])}{more}: the centreline there rests on the IMU"
        )
    degraded += list(warnings)
    if failed:
        return Verdict(FAILED, failed + degraded)
    return Verdict(DEGRADED, degraded) if degraded else Verdict()
