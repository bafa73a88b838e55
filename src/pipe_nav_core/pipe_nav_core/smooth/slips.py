"""Wheel slip found after a smoothing pass: the odometer epochs whose distance disagrees with
the smoothed path, which the next pass (and the batch smoother) leaves out."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core import batched
from pipe_nav_core.config import NOISE_EPOCH_S, NavConfig
from pipe_nav_core.geo import earth
from pipe_nav_core.model.state import SV_K
from pipe_nav_core.smooth.recording import Recording
from pipe_nav_core.types import Trajectory

Array = NDArray[np.float64]


def find_slips(
    rec: Recording,
    centre: Trajectory,
    config: NavConfig,
    n_sigma: float = 4.0,
    resolution: float = 0.0,
) -> Array:
    """Epochs whose calibrated odometer distance disagrees with the smoothed path length by more
    than n_sigma sigmas of an epoch's odometer distance (wheel slip or spin), widened by one
    epoch on each side, as (N, 2) time intervals in s. The sigma combines the white speed noise
    over the epoch and the quantization of the two readings that bound it (resolution m per
    count: variance resolution^2 / 6); with a coarse encoder the latter dominates.
    centre: the centreline of rec (:func:`pipe_nav_core.smooth.centreline.smoothed_centreline`,
    one row per recorded sample)."""
    lat, lon, h = centre.lat, centre.lon, centre.h
    step = np.empty(len(lat))  # m, from the sample before (0 for the first)
    for b in range(0, len(lat), batched.BATCH):  # in batches: bounded temporaries
        e, lo = min(b + batched.BATCH, len(lat)), max(b - 1, 0)
        enu = earth.geodetic_to_enu(lat[lo:e], lon[lo:e], h[lo:e], lat[0], lon[0], h[0])
        d = np.diff(enu, axis=0, prepend=enu[:1]) if b == 0 else np.diff(enu, axis=0)
        step[b:e] = np.linalg.norm(d, axis=1)
    k = rec.s_epoch
    n_ep = len(rec)
    path = np.bincount(k, weights=step, minlength=n_ep)
    s_odo = rec.s_odo
    d_odo = np.diff(s_odo, prepend=s_odo[:1])
    scale = 1.0 + rec.states[:, SV_K]
    odo = np.bincount(k, weights=d_odo, minlength=n_ep) * scale
    t = rec.t
    T = np.diff(t, prepend=t[:1])
    white = config.odometer_speed_sigma * np.sqrt(NOISE_EPOCH_S * T)  # sigma_T * T
    sigma = np.sqrt(white**2 + resolution**2 / 6.0)
    bad = np.abs(np.abs(odo) - path) > n_sigma * np.maximum(sigma, 1e-9)
    bad[0] = False
    bad = bad | np.r_[bad[1:], False] | np.r_[False, bad[:-1]]
    idx = np.nonzero(bad)[0]
    idx = idx[idx > 0]
    return np.stack([t[idx - 1], t[idx]], axis=-1) if len(idx) else np.zeros((0, 2))
