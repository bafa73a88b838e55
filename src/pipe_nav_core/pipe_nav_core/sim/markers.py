"""Above-ground markers: passage times and surveyed positions.

The pig passes marker k at the first time its centreline chainage reaches the marker's chainage;
the launch trap (chainage 0) is "passed" when the pig starts moving and the receive trap (end of
the pipe) when it arrives. The recorded time has an error N(0, time_sigma), drawn afresh for
each run. The surveyed position has an error N(0, sigma) per ENU axis about the true centreline
point; the survey is done once per pipe, so that error depends only on the pipe (its seed) and
the marker's chainage, and every run through the pipe shares it (as in the papers'
repeatability tests, where several runs are scored against one survey).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.geo import earth
from pipe_nav_core.sim.geometry import PipeGeometry
from pipe_nav_core.sim.motion import PigMotion
from pipe_nav_core.types import Marker

FloatArray = NDArray[np.float64]


def marker_name(k: int) -> str:
    """Name (bag frame_id) of the k-th marker: agm_00, agm_01, ..."""
    return f"agm_{k:02d}"


def make_markers(
    geometry: PipeGeometry,
    motion: PigMotion,
    chainages: FloatArray,
    time_sigma: float,
    sigma_h: float,
    sigma_v: float,
    rng: np.random.Generator,
    pipe_seed: int,
) -> tuple[list[Marker], list[Marker]]:
    """(noisy markers as recorded, true markers) at the given chainages (m, increasing).

    time_sigma: s; sigma_h, sigma_v: m survey one-sigma (east/north, up). rng draws the timing
    errors of this run; pipe_seed fixes the survey errors (see :func:`survey_errors`). Both
    lists carry sigma_enu = (sigma_h, sigma_h, sigma_v).
    """
    ch = np.asarray(chainages, dtype=np.float64).reshape(-1)
    t_true = motion.time_at_chainage(ch)
    lat, lon, h = geometry.position(ch)
    sig = (float(sigma_h), float(sigma_h), float(sigma_v))
    dt = rng.standard_normal(len(ch)) * time_sigma
    d_enu = survey_errors(pipe_seed, ch) * np.array(sig)[None, :]
    noisy: list[Marker] = []
    true: list[Marker] = []
    for k in range(len(ch)):
        name = marker_name(k)
        true.append(Marker(name, float(t_true[k]), float(lat[k]), float(lon[k]), float(h[k]), sig))
        la, lo, hh = earth.enu_to_geodetic(d_enu[k], float(lat[k]), float(lon[k]), float(h[k]))
        noisy.append(Marker(name, float(t_true[k] + dt[k]), float(la), float(lo), float(hh), sig))
    return noisy, true


def survey_errors(pipe_seed: int, chainages: FloatArray) -> FloatArray:
    """Standard-normal ENU survey errors (n, 3) of the markers at these chainages (m, >= 0).

    Each marker's draw is seeded by the pipe and its chainage to the millimetre alone, so it is
    the same in every run through the pipe and whichever other markers are surveyed with it.
    """
    ch = np.asarray(chainages, dtype=np.float64).reshape(-1)
    keys = np.rint(ch * 1000.0).astype(np.int64)
    if np.any(keys < 0):
        raise ValueError("marker chainages must be non-negative")
    return np.array(
        [np.random.default_rng([int(pipe_seed), 7003, int(k)]).standard_normal(3) for k in keys]
    ).reshape(-1, 3)
