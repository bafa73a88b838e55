"""IMU samples no pig can produce: saturated (pinned at the range limit) or shocks.

A sample is left out when it is

- **saturated**: one of a run of three or more equal readings of an axis at that axis's
  extreme over the run (the sensor's range limit: the true value is beyond it), or
- **impossible**: a specific force more than ``MAX_ACCEL`` from gravity or a rate over
  ``MAX_RATE``: a pig in a pipe does not do that, a shock to the sensor does,

with ``MARGIN_S`` on each side. What is left out becomes a hole in the IMU: a short one the
filter integrates across, a long one (the pig moving in it) a data gap (gaps.py). Units: the
samples' own, m/s^2 and rad/s; times s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pipe_nav_core import batched
from pipe_nav_core.types import SensorLog

MAX_ACCEL = 100.0  # m/s^2 (about 10 g) from gravity: beyond it, a shock
MAX_RATE = 20.0  # rad/s (1150 deg/s): beyond it, a shock
MIN_FLAT = 3  # equal readings at an axis's extreme: saturation
MARGIN_S = 0.05  # s left out on each side of a bad stretch


@dataclass(frozen=True)
class ImuFault:
    """A stretch of bad IMU samples from t0 to t1 (s): kind ``saturated`` or ``shock``;
    dropped: samples left out."""

    kind: str
    t0: float
    t1: float
    dropped: int

    def describe(self) -> str:
        what = "pinned at its range limit" if self.kind == "saturated" else "beyond what a pig does"
        return (
            f"IMU {self.kind} for {self.t1 - self.t0:.2f} s from t = {self.t0:.3f} s ({what}): "
            f"{self.dropped} samples left out"
        )


def _flat_extremes(x: np.ndarray) -> np.ndarray:
    """Samples in runs of MIN_FLAT or more equal values at the column's max or min."""
    bad = np.zeros(len(x), bool)
    for c in range(x.shape[1]):
        col = x[:, c]
        for extreme in (col.max(), col.min()):
            at = col == extreme
            if at.sum() < MIN_FLAT or abs(extreme) <= 5.0 * np.median(np.abs(col)) + 1e-12:
                continue
            edges = np.flatnonzero(np.diff(np.r_[0, at.astype(np.int8), 0]))
            for a, b in zip(edges[::2], edges[1::2], strict=True):
                if b - a >= MIN_FLAT:
                    bad[a:b] = True
    return bad


def find_imu_faults(log: SensorLog) -> tuple[np.ndarray, list[ImuFault]]:
    """(mask of the IMU samples to leave out, the faults) of a time-sorted log."""
    imu = log.imu
    n = len(imu.t)
    if n < 10:
        return np.zeros(n, bool), []
    sat = _flat_extremes(imu.gyro) | _flat_extremes(imu.accel)
    accel = batched.row_norms(imu.accel)
    g = np.median(accel)
    shock = (np.abs(np.subtract(accel, g, out=accel), out=accel) > MAX_ACCEL) | (
        batched.row_norms(imu.gyro) > MAX_RATE
    )
    del accel
    bad = sat | shock
    if not bad.any():
        return bad, []
    t = imu.t
    faults: list[ImuFault] = []
    out = np.zeros(n, bool)
    edges = np.flatnonzero(np.diff(np.r_[0, bad.astype(np.int8), 0]))
    spans = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        lo, hi = t[a] - MARGIN_S, t[b - 1] + MARGIN_S
        if spans and lo <= spans[-1][1]:
            spans[-1] = (spans[-1][0], hi, spans[-1][2] or shock[a:b].any())
        else:
            spans.append((lo, hi, bool(shock[a:b].any())))
    for lo, hi, is_shock in spans:
        k = (t >= lo) & (t <= hi)
        out |= k
        faults.append(ImuFault("shock" if is_shock else "saturated", lo + MARGIN_S,
                               hi - MARGIN_S, int(k.sum())))  # fmt: skip
    return out, faults


def without_imu_faults(log: SensorLog) -> tuple[SensorLog, list[ImuFault]]:
    """The log without its bad IMU samples (see the module), and the faults."""
    bad, faults = find_imu_faults(log)
    if not faults:
        return log, []
    return replace(log, imu=log.imu.slice(~bad)), faults
