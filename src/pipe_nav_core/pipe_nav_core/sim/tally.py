"""A simulated ILI vendor's pipe tally: the pipe's girth welds and a list of features as the
vendor's own (uncalibrated) odometer measured them.

The vendor's log distance is ``(1 + scale_error) s + noise`` of the true chainage s (m);
``missing`` of the welds are not in the tally (their joints are listed as one, twice as long)
and ``extra`` welds that are not there are added inside joints (a false call). Features
(metal loss, dents, ...) at random true chainages get the log distance from their upstream
tally weld and a clock position. The tally is written in the layout io/tally_csv.py reads:
``weld_number,log_distance_m,joint_length_m,distance_to_us_weld_m,type,clock,depth_pct,comment``
(weld rows of type ``girth weld``; feature rows name their upstream weld).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.io.atomic import atomic_write

FloatArray = NDArray[np.float64]

TALLY_COLUMNS = ["weld_number", "log_distance_m", "joint_length_m", "distance_to_us_weld_m",
                 "type", "clock", "depth_pct", "comment"]  # fmt: skip
FEATURE_KINDS = ("metal loss", "dent", "lamination", "metal loss", "girth weld anomaly")


@dataclass
class TallyRowTruth:
    """One tally row and its truth: ``cells`` as written (TALLY_COLUMNS); ``true_distance``:
    the true chainage (m) of the weld or feature (NaN for an extra weld); ``weld``: True for a
    weld row; ``true_weld``: index into the true weld list (-1 for an extra weld or a feature)."""

    cells: list[str]
    true_distance: float
    weld: bool
    true_weld: int = -1


@dataclass
class SimTally:
    """A simulated vendor tally: its rows in log-distance order and the realised errors."""

    rows: list[TallyRowTruth] = field(default_factory=list)
    scale_error: float = 0.0
    missing: list[int] = field(default_factory=list)  # true weld indices left out
    extra: int = 0

    def write_csv(self, path: str | os.PathLike[str]) -> None:
        """Write the tally CSV (atomic)."""
        with atomic_write(path, "w", newline="") as f:
            f.write(",".join(TALLY_COLUMNS) + "\n")
            f.write("".join(",".join(r.cells) + "\n" for r in self.rows))


def make_tally(
    welds: FloatArray,
    rng: np.random.Generator,
    *,
    n_features: int = 20,
    scale_error: float | None = None,
    missing: float = 0.03,
    extra: float = 0.01,
    distance_sigma: float = 0.01,
) -> SimTally:
    """The vendor tally of a pipe with true weld chainages ``welds`` (m, increasing).

    scale_error: the vendor odometer's relative scale error (default: drawn uniformly in
    +-(0.1 .. 1) %); missing, extra: shares of the welds left out and added; distance_sigma: m,
    the vendor's random error per log distance; n_features: features between the first and
    the last weld.
    """
    w = np.asarray(welds, dtype=np.float64)
    if scale_error is None:
        scale_error = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.001, 0.01))
    k = 1.0 + float(scale_error)
    keep = rng.random(len(w)) >= missing
    if len(w):
        keep[0] = keep[-1] = True  # the tally starts and ends on a weld
    items = [(float(w[i]), i) for i in np.flatnonzero(keep)]
    n_extra = int(round(extra * len(w)))
    if len(w) > 2 and n_extra:
        joints = rng.choice(len(w) - 1, size=n_extra, replace=False)
        items += [(float(w[j] + rng.uniform(0.25, 0.75) * (w[j + 1] - w[j])), -1) for j in joints]
    items.sort()
    log = k * np.array([s for s, _ in items]) + rng.normal(0.0, distance_sigma, len(items))
    log = np.maximum.accumulate(log)
    truth_s = np.array([s for s, _ in items])
    rows: list[TallyRowTruth] = []
    for n, ((s, idx), x) in enumerate(zip(items, log, strict=True)):
        joint = f"{log[n + 1] - x:.3f}" if n + 1 < len(log) else ""
        rows.append(TallyRowTruth([str(n + 1), f"{x:.3f}", joint, "", "girth weld", "", "", ""],
                                  s if idx >= 0 else float("nan"), True, idx))  # fmt: skip
    if len(w) > 1 and n_features:
        s_feat = np.sort(rng.uniform(w[0] + 0.2, w[-1] - 0.2, n_features))
        for s in s_feat:
            up = int(np.searchsorted(truth_s, s, side="right")) - 1
            x = k * s + rng.normal(0.0, distance_sigma)
            rel = max(0.0, x - log[up])
            kind = str(rng.choice(FEATURE_KINDS))
            hh, mm = int(rng.integers(1, 13)), int(rng.integers(0, 4)) * 15
            depth = f"{rng.uniform(5, 40):.0f}" if kind == "metal loss" else ""
            cells = [str(up + 1), f"{x:.3f}", "", f"{rel:.3f}", kind, f"{hh}:{mm:02d}", depth,
                     "simulated"]  # fmt: skip
            rows.append(TallyRowTruth(cells, float(s), False))
        rows.sort(key=lambda r: (float(r.cells[1]), not r.weld))
    return SimTally(rows, float(scale_error), [int(i) for i in np.flatnonzero(~keep)], n_extra)


__all__ = ["FEATURE_KINDS", "TALLY_COLUMNS", "SimTally", "TallyRowTruth", "make_tally"]
