"""Multi-run fusion: N smoothed runs through one pipe into one centreline, as ONE estimation
problem solved by sparse linear least squares (scipy.sparse).

The unknowns, per ENU axis (the axes are independent problems of the same shape):

- the pipe: its position p_k at nodes every ``spacing`` m of a common chainage (the first
  run's, the reference; the other runs are mapped onto it through their matched girth welds,
  :func:`pipe_nav_core.products.movement.align_welds`, piecewise linear between welds);
- each run's own error e_r(s), a Gauss-Markov process along the chainage at nodes every
  ``error_spacing`` m (linear in between), zero mean, of standard deviation that run's own
  smoothed sigma at the node (``sigma_enu``: small at the markers, where the run is tied, larger
  between them) and correlation length ``correlation_length`` m:
  z_j = e_j / sigma_j, z_0 ~ N(0, 1), z_j - phi z_(j-1) ~ N(0, 1 - phi^2), phi =
  exp(-error_spacing / correlation_length).

The observations: run r's smoothed position at the node's chainage, y_rk = p_k + e_r(s_k) + w,
w white with ``white_sigma`` m (what the smooth error model does not carry). The normal equations
are sparse (a band once ordered); scipy.sparse.linalg.splu solves them and gives the fused sigmas
(the diagonal of the inverse, at up to ``MAX_SIGMA_NODES`` nodes, interpolated between).
Each run's residual from the fused line (its position minus the fused one, horizontal and
vertical RMS and maximum) is reported.

What the runs share cannot average out: the markers' survey errors, to which every run through
the line is tied. Its sigma, c(s), is taken as the smallest run sigma at its local minima along
the chainage (where the runs are tied to the markers), linear in between; each run's own error
above is the rest (sqrt(sigma_r^2 - c^2), at least ``SIGMA_FLOOR_M``), and c is added to the
fused sigma (the pipe absorbs the shared error: no number of runs observes it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import splu

from pipe_nav_core.geo.attitude import dcm_from_quat, euler_from_dcm, quat_from_euler
from pipe_nav_core.geo.earth import enu_to_geodetic, geodetic_to_enu
from pipe_nav_core.products.movement import MIN_WELD_PAIRS, RunLike, align_welds, chainage_map
from pipe_nav_core.types import Datum, Trajectory

FloatArray = NDArray[np.float64]

FUSION_SPACING_M = 0.5  # pipe nodes (and output rows), m of the reference chainage
ERROR_SPACING_M = 10.0  # nodes of each run's own error, m
CORRELATION_LENGTH_M = 50.0  # of each run's own error along the chainage, m
WHITE_SIGMA_M = 0.005  # observation noise beyond the smooth error model, m
SIGMA_FLOOR_M = 0.002  # smallest sigma of a run's own error, m
MAX_SIGMA_NODES = 2000  # fused sigmas computed exactly at this many nodes at most


@dataclass(frozen=True)
class RunResidual:
    """One run's position minus the fused line over the common stretch (m), and how it was
    aligned (matched welds; 0: by its chainage alone)."""

    index: int
    rms_h: float
    max_h: float
    rms_v: float
    max_v: float
    welds_matched: int


@dataclass(frozen=True)
class FusionResult:
    """The fused centreline (reference chainage, reference map frame, sigmas from the
    problem), each run's residual and its estimated own error at the pipe nodes (R, K, 3) m."""

    centreline: Trajectory
    datum: Datum
    residuals: list[RunResidual]
    run_errors: FloatArray
    notes: list[str] = field(default_factory=list)


def _monotone(traj: Trajectory) -> tuple[FloatArray, NDArray[np.int64]]:
    """Strictly increasing chainage samples of a trajectory and their indices."""
    d = np.asarray(traj.distance, dtype=np.float64)
    ok = np.flatnonzero(np.isfinite(d))
    keep = ok[np.concatenate([[True], np.diff(np.maximum.accumulate(d[ok])) > 1e-9])]
    return d[keep], keep


def _sample(traj: Trajectory, datum: Datum, s: FloatArray) -> tuple[FloatArray, FloatArray]:
    """ENU position (N, 3) in the map frame of ``datum`` and sigma (N, 3) at chainages s."""
    d, keep = _monotone(traj)
    enu = geodetic_to_enu(np.asarray(traj.lat)[keep], np.asarray(traj.lon)[keep],
                          np.asarray(traj.h)[keep], datum.lat, datum.lon,
                          datum.alt).reshape(-1, 3)  # fmt: skip
    pos = np.column_stack([np.interp(s, d, enu[:, k]) for k in range(3)])
    if traj.sigma_enu is None:
        sig = np.full((len(s), 3), np.nan)
    else:
        sg = np.asarray(traj.sigma_enu, dtype=np.float64).reshape(-1, 3)[keep]
        sig = np.column_stack([np.interp(s, d, sg[:, k]) for k in range(3)])
    return pos, sig


def _hat(nodes: FloatArray, s: FloatArray) -> sp.csr_matrix:
    """Linear interpolation matrix (len(s), len(nodes)) from node values to chainages s."""
    j = np.clip(np.searchsorted(nodes, s, side="right") - 1, 0, len(nodes) - 2)
    w = np.clip((s - nodes[j]) / (nodes[j + 1] - nodes[j]), 0.0, 1.0)
    rows = np.concatenate([np.arange(len(s))] * 2)
    return sp.csr_matrix((np.concatenate([1.0 - w, w]), (rows, np.concatenate([j, j + 1]))),
                         shape=(len(s), len(nodes)))  # fmt: skip


def _inverse_diagonal(lu, n: int, idx: NDArray[np.int64], batch: int = 256) -> FloatArray:  # noqa: ANN001
    """Diagonal entries idx of the inverse of the factorized (n, n) matrix."""
    out = np.empty(len(idx))
    for b0 in range(0, len(idx), batch):
        cols = idx[b0 : b0 + batch]
        rhs = np.zeros((n, len(cols)))
        rhs[cols, np.arange(len(cols))] = 1.0
        x = lu.solve(rhs)
        out[b0 : b0 + len(cols)] = x[cols, np.arange(len(cols))]
    return out


def fuse_runs(
    runs: Sequence[RunLike],
    *,
    spacing: float = FUSION_SPACING_M,
    error_spacing: float = ERROR_SPACING_M,
    correlation_length: float = CORRELATION_LENGTH_M,
    white_sigma: float = WHITE_SIGMA_M,
    default_sigma: float = 0.1,
) -> FusionResult:
    """Fuse ``runs`` (the first is the reference: chainage and map frame) into one centreline;
    see the module docstring for the model and the settings (m). default_sigma: m, a run's
    error sigma where its centreline carries none (with a note)."""
    for name, v in (("spacing", spacing), ("error_spacing", error_spacing),
                    ("correlation_length", correlation_length), ("white_sigma", white_sigma),
                    ("default_sigma", default_sigma)):  # fmt: skip
        if not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"fusion {name} must be a positive number of m, not {v}")
    if len(runs) < 1:
        raise ValueError("fusion needs at least one run")
    notes: list[str] = []
    ref = runs[0]
    datum = ref.datum
    ref_welds = np.array([w.distance for w in ref.welds], dtype=np.float64)

    # chainage maps onto the reference, and the common stretch
    maps, matched = [], []
    lo, hi = -math.inf, math.inf
    for r, run in enumerate(runs):
        if r == 0:
            pairs = [(i, i) for i in range(len(ref_welds))]
            f = chainage_map(np.zeros(0), np.zeros(0))
        else:
            other = np.array([w.distance for w in run.welds], dtype=np.float64)
            pairs = align_welds(ref_welds, other) if len(ref_welds) and len(other) else []
            if len(pairs) < MIN_WELD_PAIRS:
                notes.append(f"run {r + 1}: {len(pairs)} welds matched the reference's: "
                             "aligned by its chainage alone")  # fmt: skip
                pairs = []
            ia = np.array([i for i, _ in pairs], dtype=np.int64)
            ib = np.array([j for _, j in pairs], dtype=np.int64)
            f = chainage_map(ref_welds[ia], other[ib])
            back = chainage_map(other[ib], ref_welds[ia])
        d, _ = _monotone(run.trajectory)
        if len(d) < 2:
            raise ValueError(f"run {r + 1}: fewer than two samples along the chainage")
        a, b = (float(d[0]), float(d[-1])) if r == 0 else (float(back(d[0])), float(back(d[-1])))
        lo, hi = max(lo, a), min(hi, b)
        maps.append(f)
        matched.append(len(pairs))
    if not hi - lo > 2.0 * spacing:
        raise ValueError(f"the runs share no stretch of pipe ({lo:.1f} to {hi:.1f} m)")

    s = np.arange(lo, hi + 0.5 * spacing, spacing)
    s = s[s <= hi]
    k_n = len(s)
    n_e = max(2, int(math.ceil((hi - lo) / error_spacing)) + 1)
    u = np.linspace(lo, hi, n_e)
    phi = math.exp(-(u[1] - u[0]) / correlation_length)
    n_r = len(runs)
    y = np.empty((n_r, k_n, 3))
    sig_obs = np.empty((n_r, k_n, 3))
    sig_err = np.empty((n_r, n_e, 3))
    for r, run in enumerate(runs):
        y[r], sig_obs[r] = _sample(run.trajectory, datum, maps[r](s))
        _, sig_err[r] = _sample(run.trajectory, datum, maps[r](u))
        if not np.isfinite(sig_err[r]).all():
            notes.append(f"run {r + 1}: no sigmas in its centreline: {default_sigma} m assumed")
            sig_err[r] = np.where(np.isfinite(sig_err[r]), sig_err[r], default_sigma)
    common = _shared_sigma(s, sig_obs)
    shared_u = np.stack([np.interp(u, s, common[:, k]) for k in range(3)], axis=1)
    sig_err = np.sqrt(np.maximum(sig_err**2 - shared_u[None] ** 2, SIGMA_FLOOR_M**2))

    # the design matrix (same sparsity for the three axes): [pipe | e_1 | ... | e_R]
    n_x = k_n + n_r * n_e
    hat = _hat(u, s)
    eye_k = sp.identity(k_n, format="csr")
    obs_blocks = [sp.hstack([eye_k] + [hat if q == r else sp.csr_matrix((k_n, n_e))
                                       for q in range(n_r)]) for r in range(n_r)]  # fmt: skip
    a_obs = sp.vstack(obs_blocks, format="csr") / white_sigma
    i_j = np.arange(1, n_e)
    fused = np.empty((k_n, 3))
    sigma = np.empty((k_n, 3))
    errors = np.empty((n_r, k_n, 3))
    step = max(1, int(math.ceil(k_n / MAX_SIGMA_NODES)))
    at = np.unique(np.concatenate([np.arange(0, k_n, step), [k_n - 1]]))
    for axis in range(3):
        prior_blocks = []
        for r in range(n_r):
            inv = 1.0 / sig_err[r, :, axis]
            c = 1.0 / math.sqrt(1.0 - phi * phi)
            rows = np.concatenate([[0], i_j, i_j])
            cols = r * n_e + np.concatenate([[0], i_j, i_j - 1]) + k_n
            vals = np.concatenate([[inv[0]], c * inv[1:], -c * phi * inv[:-1]])
            prior_blocks.append(sp.csr_matrix((vals, (rows, cols)), shape=(n_e, n_x)))
        a = sp.vstack([a_obs] + prior_blocks, format="csc")
        b = np.concatenate([y[:, :, axis].reshape(-1) / white_sigma, np.zeros(n_r * n_e)])
        normal = (a.T @ a).tocsc()
        lu = splu(normal, permc_spec="MMD_AT_PLUS_A")  # symmetric: little fill
        x = lu.solve(a.T @ b)
        fused[:, axis] = x[:k_n]
        e_nodes = x[k_n:].reshape(n_r, n_e)
        errors[:, :, axis] = (hat @ e_nodes.T).T
        var = _inverse_diagonal(lu, n_x, at)
        var_k = np.maximum(np.interp(np.arange(k_n), at, var), 0.0)
        sigma[:, axis] = np.sqrt(var_k + common[:, axis] ** 2)

    residuals = []
    for r in range(n_r):
        res = y[r] - fused
        h = np.hypot(res[:, 0], res[:, 1])
        v = np.abs(res[:, 2])
        residuals.append(RunResidual(r + 1, float(np.sqrt(np.mean(h**2))), float(h.max()),
                                     float(np.sqrt(np.mean(v**2))), float(v.max()),
                                     matched[r]))  # fmt: skip
    return FusionResult(_trajectory(ref.trajectory, datum, s, fused, sigma), datum, residuals,
                        errors, notes)  # fmt: skip


def _shared_sigma(s: FloatArray, sig_obs: FloatArray) -> FloatArray:
    """(K, 3) sigma of the error all runs share at chainages s (m; module docstring): the
    smallest run sigma (sig_obs (R, K, 3)) through its local minima, linear in between."""
    low = np.nan_to_num(np.min(sig_obs, axis=0), nan=0.0)
    out = np.empty_like(low)
    for k in range(3):
        v = low[:, k]
        edge = np.r_[np.inf, v, np.inf]
        idx = np.flatnonzero((v <= edge[:-2]) & (v <= edge[2:]))
        out[:, k] = np.interp(s, s[idx], v[idx]) if len(idx) else v
    return np.minimum(out, low)


def _trajectory(
    ref: Trajectory, datum: Datum, s: FloatArray, enu: FloatArray, sigma: FloatArray
) -> Trajectory:
    """The fused line as a Trajectory: the reference's times at the nodes' chainage, attitude
    from the fused axis (pitch, azimuth) and the reference's roll."""
    d, keep = _monotone(ref)
    t = np.interp(s, d, np.asarray(ref.t, dtype=np.float64)[keep])
    lat, lon, h = enu_to_geodetic(enu, datum.lat, datum.lon, datum.alt)
    tangent = np.gradient(enu, s, axis=0) if len(s) > 1 else np.array([[0.0, 1.0, 0.0]])
    az = np.arctan2(tangent[:, 0], tangent[:, 1])
    pitch = np.arctan2(tangent[:, 2], np.hypot(tangent[:, 0], tangent[:, 1]))
    ref_roll, _, _ = euler_from_dcm(dcm_from_quat(np.asarray(ref.quat_nb)[keep]))
    roll = np.interp(s, d, np.unwrap(ref_roll))
    dt = np.gradient(t) if len(t) > 1 else np.ones(1)
    vel = np.gradient(enu, axis=0) / np.where(dt > 0, dt, 1.0)[:, None]
    return Trajectory(t=t, lat=np.asarray(lat), lon=np.asarray(lon), h=np.asarray(h), vel_n=vel,
                      quat_nb=quat_from_euler(roll, pitch, az), distance=s.copy(),
                      sigma_enu=sigma)  # fmt: skip


__all__ = [
    "CORRELATION_LENGTH_M",
    "ERROR_SPACING_M",
    "FUSION_SPACING_M",
    "WHITE_SIGMA_M",
    "FusionResult",
    "RunResidual",
    "fuse_runs",
]
