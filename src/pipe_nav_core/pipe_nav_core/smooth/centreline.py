"""What a smoothing run gives: the smoothed centreline at the IMU rate, its chainage, the
forward filter's estimates, the markers' residuals and the summary, in a :class:`SmoothResult`.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core import batched
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.anchoring import FreeHeading
from pipe_nav_core.filter.navigator import Navigator
from pipe_nav_core.geo import earth
from pipe_nav_core.model.state import SV_DIST, SV_H, SV_LAT, SV_LON, SV_Q, SV_T, SV_VEL
from pipe_nav_core.smooth import samples
from pipe_nav_core.smooth.recording import Recording
from pipe_nav_core.types import Datum, Marker, Trajectory

if TYPE_CHECKING:
    from pipe_nav_core.products import IntegrityReport
    from pipe_nav_core.products.welds import Weld

Array = NDArray[np.float64]
PARK_BYTES = 256 << 20  # a kept centreline larger than this waits on disk (Parked)


@dataclass
class SmoothResult:
    """Result of :func:`pipe_nav_core.smooth.passes.smooth_log`.

    centreline: smoothed trajectory at the IMU sample times (sigma_enu filled);
    forward: forward-filter estimates per epoch (what /pipe_nav/odometry carries);
    datum: origin of map (first marker); markers: the markers used;
    marker_residuals: name -> (3,) ENU m, smoothed position minus survey at the passage;
    summary: figures for people (see :func:`summarize`); config: the settings the run was
    smoothed with (the IMU model chosen for it); products: its integrity products, when the
    pipeline computed them (products.integrity_report); welds: its girth welds
    (products.welds.detect_welds), None when the pipeline did not look (no magnetometer).
    """

    centreline: Trajectory
    forward: Trajectory
    datum: Datum
    markers: list[Marker]
    marker_residuals: dict[str, Array]
    summary: dict[str, object] = field(default_factory=dict)
    config: NavConfig | None = None
    products: IntegrityReport | None = None
    welds: list[Weld] | None = None


class Parked:
    """A smoothing result whose centreline waits on disk while another pass runs, so that two
    centrelines at the IMU rate are never in memory (at 100 km one is 1.4 GB): its arrays as
    .npy files in a temporary directory, removed by :meth:`restore` or when this goes."""

    def __init__(self, result: SmoothResult) -> None:
        self.result = result
        self._dir = tempfile.TemporaryDirectory(prefix="pipe_nav_parked_")
        c = result.centreline
        self._names = [f.name for f in fields(c) if isinstance(getattr(c, f.name), np.ndarray)]
        for name in self._names:
            np.save(os.path.join(self._dir.name, f"{name}.npy"), getattr(c, name))
            setattr(c, name, None)

    @staticmethod
    def worth(result: SmoothResult) -> bool:
        """Whether the result's centreline is large enough to wait on disk (PARK_BYTES)."""
        c = result.centreline
        size = sum(v.nbytes for v in vars(c).values() if isinstance(v, np.ndarray))
        return size > PARK_BYTES

    def restore(self) -> SmoothResult:
        """The result as it was (the same arrays' values, read back)."""
        c = self.result.centreline
        for name in self._names:
            setattr(c, name, np.load(os.path.join(self._dir.name, f"{name}.npy")))
        self._dir.cleanup()
        return self.result


def smoothed_centreline(rec: Recording, e_pose: Array, var: Array) -> Trajectory:
    """The smoothed corrections applied to the recorded per-sample nominal trajectory.

    e_pose (K, 6): the columns ``rec.pose`` (position m, attitude rad) of the smoothed
    corrections to the filter's estimates, var (K, 6) their variances (m^2, rad^2); the
    correction relative to the linearization point of epoch k is x_upd[k] + e[k]; a block's
    nominal starts on lin[k - 1] and ends end_offset[k] short of lin[k]; in between the
    correction is interpolated in time. The centreline is made in the recording's own
    per-sample arrays (:meth:`Recording.take_nominal`): the recording has no nominal after.
    """
    if e_pose.shape[1:] != (len(rec.pose),) or var.shape[1:] != (len(rec.pose),):
        raise ValueError(f"smoothed_centreline: e_pose {e_pose.shape}, var {var.shape}: "
                         f"not rec.pose's {len(rec.pose)} columns")  # fmt: skip
    d_lin = rec.x_upd_pose + e_pose
    d_end = d_lin + rec.end_offset  # its columns are pose's
    t_ep = rec.t
    k_of = rec.s_epoch
    # the nominal, overwritten with the centreline (the kernel writes in place)
    t, lat, lon, h, q = (np.ascontiguousarray(a, dtype=np.float64) for a in rec.take_nominal())
    N = len(t)
    sig_p, sig_a = np.empty((N, 3)), np.empty((N, 3))
    arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in (d_lin, d_end, var)]
    samples.correct_samples(t, lat, lon, h, q, np.ascontiguousarray(k_of, dtype=np.int32),
                            np.ascontiguousarray(t_ep), *arrays, sig_p, sig_a)  # fmt: skip
    distance = arc_chainage(lat, lon, h, q)
    return Trajectory(t, lat, lon, h, enu_velocity(t, lat, lon, h), q, distance, sig_p, sig_a)


def enu_velocity(t: Array, lat: Array, lon: Array, h: Array) -> Array:
    """Velocity (N, 3) m/s in the ENU frame at the first sample: ``np.gradient`` of the
    positions (lat, lon rad, h m) over the times t (s, increasing), batched.BATCH samples at a
    time (:func:`pipe_nav_core.batched.gradient_of`: the values np.gradient gives)."""
    if not len(t):
        return np.zeros((0, 3))

    def enu(lo: int, hi: int) -> Array:
        return earth.geodetic_to_enu(lat[lo:hi], lon[lo:hi], h[lo:hi], lat[0], lon[0], h[0])

    return batched.gradient_of(enu, t, batched.BATCH)


def arc_chainage(lat: Array, lon: Array, h: Array, quat_nb: Array) -> Array:
    """Chainage (m, 0 at the first sample) as the smoothed path's length, signed along the
    body axis (backing up counts down): a slipping, stuck or spiking wheel does not corrupt
    it. Steps in the local ENU of each sample (lat, lon rad, h m; quat_nb base_link->ENU)."""
    if len(lat) < 2:
        return np.zeros(len(lat))
    dlon = np.diff(earth.unwrapped_lon(lon))
    along = np.empty(len(lat) - 1)
    c = [np.ascontiguousarray(a, dtype=np.float64) for a in (lat, dlon, h, quat_nb)]
    samples.axis_steps(*c, along)
    return np.r_[0.0, np.cumsum(along)]


def forward_trajectory(rec: Recording) -> Trajectory:
    """The forward filter's estimates, one per epoch (copies: the recording may go)."""
    st = rec.states
    var = np.maximum(rec.pose_variances(), 0.0)  # position, attitude; < 0 only diverged
    return Trajectory(
        t=st[:, SV_T].copy(),
        lat=st[:, SV_LAT].copy(),
        lon=st[:, SV_LON].copy(),
        h=st[:, SV_H].copy(),
        vel_n=st[:, SV_VEL].copy(),
        quat_nb=st[:, SV_Q].copy(),
        distance=st[:, SV_DIST].copy(),
        sigma_enu=np.sqrt(var[:, :3]),
        sigma_att=np.sqrt(var[:, 3:]),
    )


def with_free_heading(traj: Trajectory, free: FreeHeading | None) -> Trajectory:
    """traj with the uncertainty of the heading the filter left unanchored (FreeHeading)
    added to its horizontal position and azimuth sigmas (in place; returned)."""
    if free is None or traj.sigma_enu is None or traj.sigma_att is None:
        return traj
    extra = free.variances(traj.t, traj.lat, traj.lon, traj.h)
    traj.sigma_enu[:, :2] = np.sqrt(traj.sigma_enu[:, :2] ** 2 + extra[:, :2])
    traj.sigma_att[:, 2] = np.sqrt(traj.sigma_att[:, 2] ** 2 + extra[:, 2])
    return traj


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
            i = int(np.searchsorted(traj.t, m.t))
            s = slice(max(i - 1, 0), i + 1)  # the samples around the passage
            enu = earth.geodetic_to_enu(traj.lat[s], traj.lon[s], traj.h[s], m.lat, m.lon, m.alt)
            out[m.name] = np.array([np.interp(m.t, traj.t[s], enu[:, c]) for c in range(3)])
    return out


def summarize(result: SmoothResult, nav: Navigator) -> dict[str, object]:
    """Figures for people: distance, duration, markers, rejected updates, the straight-pipe
    and section-direction updates the taken pass applied, calibration; and
    the markers whose passage inflated the filter's covariance (faults.markers tests them)."""
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
        "straight_pipe_updates": int(diag.get("accepted_straight", 0)),
        "section_direction_updates": int(diag.get("accepted_direction", 0)),
        "odometer_scale": float(1.0 + s.k) if s else 1.0,
        "gyro_bias_deg_h": [float(x) for x in np.degrees(s.bg) * 3600] if s else [],
        "accel_bias_mg": [float(x) for x in s.ba / 9.80665 * 1e3] if s else [],
        "max_sigma_h_between_markers_m": float(sig_h[inside].max()) if inside.any() else 0.0,
        "max_marker_residual_m": float(
            max((np.linalg.norm(v) for v in result.marker_residuals.values()), default=0.0)
        ),
        "warnings": nav.model_warnings(),
        "markers_inflated": nav.inflated_markers,
        "markers_after_odometer_loss": nav.after_odometer_loss,
    }
    return out
