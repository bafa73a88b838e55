"""Offline smoothing of a whole run: forward filter, then RTS or two-filter fusion, with a
re-linearization pass, and the smoothed centreline at the IMU rate.

Methods (``method``):
- ``forward``: the forward filter alone (what the live node sees);
- ``rts``: Rauch-Tung-Striebel over the recorded forward filter;
- ``two-filter``: the forward filter fused with a filter run on the time-reversed data
  (seed 001 RTS-FC, seed 004).
Passes repeat (up to ``iterations``) from the smoothed initial attitude, biases, odometer
scale and boresight of the previous pass, so that the linearization is about a trajectory
close to the truth (an iterated smoother), until the smoothed correction of the initial
attitude falls below CONVERGED_RAD; odometer epochs that disagree with the previous pass's
smoothed path (wheel slip) are left out of the next pass.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from . import attitude as att
from . import earth
from .config import NavConfig
from .engine import Navigator, Recording
from .smoothing import fuse_covariance, rts
from .state import Layout, NavState
from .types import (
    Datum,
    ImuSamples,
    MagSamples,
    Marker,
    OdometerSamples,
    SensorLog,
    Trajectory,
    markers_sorted,
)

Array = NDArray[np.float64]
METHODS = ("forward", "rts", "two-filter")
CONVERGED_RAD = 1e-4  # rad: initial-attitude correction below which another pass is not needed


@dataclass
class SmoothResult:
    """Result of :func:`smooth_log`.

    centreline: smoothed trajectory at the IMU sample times (sigma_enu filled);
    forward: forward-filter estimates per epoch (what /pipe_nav/odometry carries);
    datum: origin of map (first marker); markers: the markers used;
    marker_residuals: name -> (3,) ENU m, smoothed position minus survey at the passage;
    summary: figures for people (see :func:`summarize`).
    """

    centreline: Trajectory
    forward: Trajectory
    datum: Datum
    markers: list[Marker]
    marker_residuals: dict[str, Array]
    summary: dict[str, object] = field(default_factory=dict)
    final_state: NavState | None = None


def reverse_log(log: SensorLog) -> SensorLog:
    """The log in reversed time (t -> -t): IMU sample i (the mean over (t[i-1], t[i]]) becomes
    a sample stamped -t[i-1] with negated rate; odometer speed negated; markers re-stamped."""
    imu = log.imu
    t = -imu.t[:-1][::-1]
    rimu = ImuSamples(t, -imu.gyro[1:][::-1], imu.accel[1:][::-1])
    o = log.odometer
    rodo = OdometerSamples(-o.t[::-1], o.distance[::-1], -o.speed[::-1])
    m = log.mag
    rmag = MagSamples(-m.t[::-1], m.field[::-1])
    markers = [
        Marker(k.name, -k.t, k.lat, k.lon, k.alt, k.sigma_enu)
        for k in markers_sorted(log.markers)[::-1]
    ]
    return SensorLog(rimu, rodo, rmag, markers)


def _flip(layout: Layout) -> Array:
    """Signs mapping reversed-time error states to forward ones (velocity, gyro bias negate)."""
    s = np.ones(layout.n)
    if layout.vel is not None:
        s[layout.vel] = -1.0
    s[layout.bg] = -1.0
    return s


def _flip_state(x: NavState) -> NavState:
    y = x.copy()
    y.vel_n = -y.vel_n
    y.bg = -y.bg
    return y


def run_forward(
    log: SensorLog,
    config: NavConfig,
    *,
    initial: NavState | None = None,
    reverse: bool = False,
    epoch_times: Array | None = None,
    odometer_exclude: Array | None = None,
) -> Navigator:
    """One recorded filter pass over a time-sorted log."""
    nav = Navigator(
        config,
        survey=log.markers,
        record=True,
        reverse=reverse,
        initial=initial,
        epoch_times=epoch_times,
        odometer_exclude=odometer_exclude,
    )
    nav.run(log)
    nav.poll()
    if nav.recording is None or not nav.recording.t:
        raise ValueError("no navigation solution: the log has no usable IMU data after alignment")
    return nav


def smooth_log(
    log: SensorLog,
    config: NavConfig,
    *,
    method: str = "rts",
    iterations: int = 5,
    progress: Callable[[str], None] | None = None,
) -> SmoothResult:
    """Smooth a whole time-sorted log (IMU in imu_link as recorded) and return the centreline."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if len(log.imu) < 10:
        raise ValueError("the log has fewer than 10 IMU samples")
    say = progress or (lambda _msg: None)
    layout = Layout(config.mode, config.gyro_error_states)
    markers = markers_sorted(log.markers)
    initial: NavState | None = None
    exclude: Array | None = None
    best: tuple[tuple[int, float], SmoothResult] | None = None
    for it in range(max(1, iterations)):
        say(f"forward filter (pass {it + 1})")
        nav = run_forward(log, config, initial=initial, odometer_exclude=exclude)
        rec = nav.recording
        assert rec is not None
        if method == "forward":
            e = np.zeros((len(rec.t), layout.n))
            P_s = np.array(rec.P_upd)
        elif method == "rts":
            say("RTS smoother")
            e, P_s = rts(rec.P_upd, rec.P_pred, rec.phi, rec.dx)
        else:
            say("backward filter")
            e, P_s = _two_filter(log, config, rec, layout)
        centre = _centreline(rec, e, P_s, layout)
        datum = nav.datum or Datum(rec.states[0].lat, rec.states[0].lon, rec.states[0].h)
        result = SmoothResult(
            centre,
            _forward_trajectory(rec, layout),
            datum,
            markers,
            marker_residuals(centre, markers),
            final_state=nav.state,
        )
        result.summary = summarize(result, nav)
        result.summary["passes"] = it + 1
        # a pass is better when it rejects fewer markers, then when it fits them more closely
        quality = (
            int(result.summary["markers_rejected"]),
            float(result.summary["max_marker_residual_m"]),
        )
        if best is None or quality < best[0]:
            best = (quality, result)
        if method == "forward":
            break
        initial = rec.states[0].inject(e[0], layout)
        new_exclude = find_slips(rec, centre, config) if layout.has_vel else None
        same_slips = (
            exclude is not None and new_exclude is not None and np.array_equal(exclude, new_exclude)
        )
        if float(np.linalg.norm(e[0][layout.att])) < CONVERGED_RAD and (
            same_slips or new_exclude is None
        ):
            break
        exclude = new_exclude
    assert best is not None
    best[1].summary["passes_run"] = it + 1
    return best[1]


def find_slips(
    rec: Recording, centre: Trajectory, config: NavConfig, n_sigma: float = 4.0
) -> Array:
    """Epochs whose calibrated odometer distance disagrees with the smoothed path length by more
    than n_sigma odometer sigmas (wheel slip or spin), widened by one epoch on each side, as
    (N, 2) time intervals in s."""
    enu = earth.geodetic_to_enu(
        centre.lat, centre.lon, centre.h, centre.lat[0], centre.lon[0], centre.h[0]
    )
    step = np.linalg.norm(np.diff(enu, axis=0, prepend=enu[:1]), axis=1)
    k = np.concatenate(rec.s_epoch)
    n_ep = len(rec.t)
    path = np.bincount(k, weights=step, minlength=n_ep)
    s_odo = np.concatenate(rec.s_odo)
    d_odo = np.diff(s_odo, prepend=s_odo[:1])
    scale = 1.0 + np.array([st.k for st in rec.states])
    odo = np.bincount(k, weights=d_odo, minlength=n_ep) * scale
    t = np.asarray(rec.t)
    T = np.diff(t, prepend=t[:1])
    bad = np.abs(np.abs(odo) - path) > n_sigma * config.odometer_speed_sigma * np.maximum(T, 1e-9)
    bad[0] = False
    bad = bad | np.r_[bad[1:], False] | np.r_[False, bad[:-1]]
    idx = np.nonzero(bad)[0]
    idx = idx[idx > 0]
    return np.stack([t[idx - 1], t[idx]], axis=-1) if len(idx) else np.zeros((0, 2))


def _two_filter(
    log: SensorLog, config: NavConfig, rec: Recording, layout: Layout
) -> tuple[Array, Array]:
    t_f = np.asarray(rec.t)
    back = run_forward(reverse_log(log), config, reverse=True, epoch_times=-t_f[::-1])
    rb = back.recording
    assert rb is not None
    t_b = -np.asarray(rb.t)
    flip = _flip(layout)
    e = np.zeros((len(t_f), layout.n))
    P_s = np.array(rec.P_upd)
    j_of = {round(tb * 1e6): j for j, tb in enumerate(t_b)}
    for k, tk in enumerate(t_f):
        j = j_of.get(round(tk * 1e6))
        if j is None or j == 0:
            continue  # no independent backward estimate here (its alignment or beyond)
        xb = _flip_state(rb.states[j].inject(-rb.dx[j], layout))  # backward prediction
        Pb = rb.P_pred[j] * np.outer(flip, flip)
        d = xb.difference(rec.states[k], layout)
        e[k], P_s[k] = fuse_covariance(np.zeros(layout.n), rec.P_upd[k], d, Pb)
    return e, P_s


def _centreline(rec: Recording, e: Array, P_s: Array, layout: Layout) -> Trajectory:
    """Apply the smoothed corrections to the per-sample nominal trajectory."""
    t = np.concatenate(rec.s_t)
    k = np.concatenate(rec.s_epoch)
    t_ep = np.asarray(rec.t)
    frac = (t - t_ep[k - 1]) / np.maximum(t_ep[k] - t_ep[k - 1], 1e-12)
    dx = np.asarray(rec.dx)
    corr = (1.0 - frac)[:, None] * e[k - 1] + frac[:, None] * (e[k] + dx[k])
    lat = np.concatenate(rec.s_lat)
    lon = np.concatenate(rec.s_lon)
    h = np.concatenate(rec.s_h)
    dlat, dlon, dh = earth.enu_to_geodetic_increment(corr[:, layout.pos], lat, h)
    lat, lon, h = lat + dlat, lon + dlon, h + dh
    q = att.quat_normalize(
        att.quat_mul(att.quat_from_rotvec(corr[:, layout.att]), np.concatenate(rec.s_q))
    )
    var = np.einsum("kii->ki", P_s)
    var_s = (1.0 - frac)[:, None] * var[k - 1] + frac[:, None] * var[k]
    sig_p = np.sqrt(np.maximum(var_s[:, layout.pos], 0.0))
    sig_a = np.sqrt(np.maximum(var_s[:, layout.att], 0.0))
    kvals = np.array([s.k for s in rec.states]) + e[:, layout.k.start]
    k_s = (1.0 - frac) * kvals[k - 1] + frac * kvals[k]
    s_odo = np.concatenate(rec.s_odo)
    ds = np.diff(np.r_[s_odo[0], s_odo])
    distance = np.cumsum((1.0 + k_s) * ds)
    enu = earth.geodetic_to_enu(lat, lon, h, lat[0], lon[0], h[0])
    vel = np.gradient(enu, t, axis=0) if len(t) > 1 else np.zeros((len(t), 3))
    return Trajectory(t, lat, lon, h, vel, q, distance, sig_p, sig_a)


def _forward_trajectory(rec: Recording, layout: Layout) -> Trajectory:
    st = rec.states
    P = np.asarray(rec.P_upd)
    var = np.einsum("kii->ki", P)
    return Trajectory(
        t=np.asarray(rec.t),
        lat=np.array([s.lat for s in st]),
        lon=np.array([s.lon for s in st]),
        h=np.array([s.h for s in st]),
        vel_n=np.array([s.vel_n for s in st]),
        quat_nb=np.array([s.q_nb for s in st]),
        distance=np.array([s.distance for s in st]),
        sigma_enu=np.sqrt(var[:, layout.pos]),
        sigma_att=np.sqrt(var[:, layout.att]),
    )


def interpolate_enu(traj: Trajectory, times: Array, datum: Datum) -> Array:
    """ENU positions (m) of a trajectory at the given times (linear interpolation)."""
    enu = earth.geodetic_to_enu(traj.lat, traj.lon, traj.h, datum.lat, datum.lon, datum.alt)
    return np.stack([np.interp(times, traj.t, enu[:, i]) for i in range(3)], axis=-1)


def marker_residuals(traj: Trajectory, markers: list[Marker]) -> dict[str, Array]:
    """name -> estimate minus survey, ENU m, at each marker passage inside the trajectory."""
    out: dict[str, Array] = {}
    if not len(traj):
        return out
    for m in markers:
        if traj.t[0] <= m.t <= traj.t[-1]:
            d = Datum(m.lat, m.lon, m.alt)
            out[m.name] = interpolate_enu(traj, np.array([m.t]), d)[0]
    return out


def summarize(result: SmoothResult, nav: Navigator) -> dict[str, object]:
    """Figures for people: distance, duration, markers, rejected updates, calibration."""
    c = result.centreline
    diag = nav.diagnostics()
    s = nav.state
    inside = (
        (c.t >= result.markers[0].t) & (c.t <= result.markers[-1].t)
        if result.markers
        else np.ones(len(c), bool)
    )
    sig_h = (
        np.hypot(c.sigma_enu[:, 0], c.sigma_enu[:, 1])
        if c.sigma_enu is not None
        else np.zeros(len(c))
    )
    out: dict[str, object] = {
        "distance_m": float(c.distance[-1]) if len(c) else 0.0,
        "duration_s": float(c.t[-1] - c.t[0]) if len(c) else 0.0,
        "markers_total": len(result.markers),
        "markers_used": int(diag.get("accepted_marker", 0)),
        "markers_rejected": int(diag.get("rejected_marker", 0)),
        "rejected_updates": {k[9:]: v for k, v in diag.items() if k.startswith("rejected_") and v},
        "odometer_scale": float(1.0 + s.k) if s else 1.0,
        "gyro_bias_deg_h": [float(x) for x in np.degrees(s.bg) * 3600] if s else [],
        "accel_bias_mg": [float(x) for x in s.ba / 9.80665 * 1e3] if s else [],
        "max_sigma_h_between_markers_m": float(sig_h[inside].max()) if inside.any() else 0.0,
        "max_marker_residual_m": float(
            max((np.linalg.norm(v) for v in result.marker_residuals.values()), default=0.0)
        ),
    }
    return out
