"""Ground movement between two runs through one pipe: a known, smooth displacement field.

A :class:`GroundMovement` moves a stretch of the pipe sideways (``lateral``, m, positive to the
right looking downstream) and down (``settlement``, m, positive downward) with the smooth
bell of :class:`~pipe_nav_core.sim.geometry.Sag`: zero displacement and zero extra curvature at
both ends, the full offset in the middle, (1 - cos 2 pi x)^2 / 4 in between. It is added to the
pipe as extra sag features, so the moved pipe keeps its length along the axis, its girth welds
(the same chainages: the welds are drawn from the scenario's pipe seed) and its markers: a run
through it with :func:`simulate_moved` is a later inspection of the same line after the ground
moved. :func:`true_displacement` is the exact field (moved minus original position at the same
chainage, ENU m) to score a comparison against.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.geo import earth
from pipe_nav_core.sim.geometry import Sag
from pipe_nav_core.sim.run import SimRun, simulate
from pipe_nav_core.sim.scenarios import Scenario
from pipe_nav_core.types import Datum

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class GroundMovement:
    """Movement of the pipe over ``length`` m of chainage from ``start`` m: peak ``lateral``
    offset (m, to the right looking downstream) and peak ``settlement`` (m, downward), both
    reached at start + length / 2."""

    start: float
    length: float = 60.0
    lateral: float = 0.2
    settlement: float = 0.05

    def __post_init__(self) -> None:
        if not self.length > 0.0:
            raise ValueError(f"ground movement length must be positive, not {self.length}")
        if self.start < 0.0:
            raise ValueError(f"ground movement start must be >= 0, not {self.start}")

    @property
    def end(self) -> float:
        """Chainage where the movement ends, m."""
        return self.start + self.length

    def features(self) -> list[Sag]:
        """The sag features (at true chainages, m) that displace the pipe."""
        out = []
        if self.lateral:
            out.append(Sag(self.start, self.length, self.lateral, "h"))
        if self.settlement:
            out.append(Sag(self.start, self.length, self.settlement, "v"))
        return out


def moved_scenario(scn: Scenario, movements: Sequence[GroundMovement]) -> Scenario:
    """The scenario's pipe after the ground ``movements`` (same pipe seed: same welds, markers'
    survey and field bends); features are stored unscaled, so the chainages given here are
    divided by the scenario's ``length_scale``."""
    k = scn.length_scale
    extra = [Sag(f.chainage / k, f.length / k, f.depth, f.plane)
             for m in movements for f in m.features()]  # fmt: skip
    for m in movements:
        if m.end > scn.total_length:
            raise ValueError(f"ground movement {m.start}-{m.end} m runs past the pipe's end "
                             f"({scn.total_length} m)")  # fmt: skip
    return replace(scn, features=tuple(scn.features) + tuple(extra))


def simulate_moved(
    scn: Scenario, movements: Sequence[GroundMovement], seed: int, **kwargs: object
) -> SimRun:
    """A run (``seed`` draws the motion and the sensor errors) through the moved pipe."""
    return simulate(moved_scenario(scn, movements), seed, **kwargs)  # type: ignore[arg-type]


def true_displacement(
    scn: Scenario, movements: Sequence[GroundMovement], s: ArrayLike, datum: Datum
) -> FloatArray:
    """Exact displacement (N, 3) ENU m in the map frame of ``datum`` at true chainages ``s`` (m):
    moved pipe minus original pipe."""
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    before = scn.build_geometry().position(s)
    after = moved_scenario(scn, movements).build_geometry().position(s)
    a = earth.geodetic_to_enu(*before, datum.lat, datum.lon, datum.alt).reshape(-1, 3)
    b = earth.geodetic_to_enu(*after, datum.lat, datum.lon, datum.alt).reshape(-1, 3)
    return b - a


__all__ = ["GroundMovement", "moved_scenario", "simulate_moved", "true_displacement"]
