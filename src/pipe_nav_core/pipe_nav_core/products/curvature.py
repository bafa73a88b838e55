"""The pipe's curvature along its chainage, from the smoothed attitude, with a sigma per value.

The pipe axis is the smoothed body x axis (base_link x in the local ENU frame); a constant
odometer/IMU misalignment turns it by a constant and leaves its changes alone. Along the
chainage the axis is sampled on a monotone track (the time at which the run's ``distance_m``
first reaches each step, so stops and backward creeps do not count twice) whose length is the
arc length of the smoothed positions (a slipping wheel does not stretch the curvature).

The curvature at chainage s is the mean over a window of ``w`` metres of arc centred on s:
the angle between the axis at both ends of the window divided by ``w`` (exact for an arc, and
a boxcar filter of the pointwise curvature otherwise). Its components, per INTERFACES.md:
vertical = d(pitch)/ds (positive bending upward), horizontal = cos(pitch) d(azimuth)/ds
(positive turning right), the plane = direction of the centre of curvature about the axis,
clockwise from the top seen looking downstream.

Resolution against noise: features shorter than the window are averaged down (a bend of arc
length L < w shows its full angle but a peak curvature of angle / w), while the noise of the
relative attitude over the window falls as w^-1.5 (angle random walk over the window's
traverse time, divided by w). The sigma of each value is that model
(:func:`relative_angle_sigma`): the smoothed attitude's change over a few seconds is the gyro
integral, which no aiding constrains at that scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core import batched
from pipe_nav_core.geo.attitude import body_x_axis
from pipe_nav_core.geo.earth import radii, unwrapped_lon
from pipe_nav_core.io.centreline import chainage_times, interpolate_trajectory
from pipe_nav_core.model.sensors import ImuSpec
from pipe_nav_core.types import Trajectory

FloatArray = NDArray[np.float64]

TRACK_STEP_M = 0.02  # m, chainage step of the axis track (about an IMU sample at 2 m/s)


@dataclass(frozen=True)
class AxisTrack:
    """The pipe axis on a fine, monotone chainage grid.

    distance: (N,) m, the run's distance_m (increasing); arc: (N,) m, arc length of the
    smoothed positions from the first point; t: (N,) s; lat, lon: rad; h: m ellipsoidal;
    axis: (N, 3) unit pipe axis in local ENU; sigma_h, sigma_v: (N,) m, one-sigma horizontal
    and vertical position (NaN when the trajectory has none).
    """

    distance: FloatArray
    arc: FloatArray
    t: FloatArray
    lat: FloatArray
    lon: FloatArray
    h: FloatArray
    axis: FloatArray
    sigma_h: FloatArray
    sigma_v: FloatArray

    def at_arc(self, a: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(axis (M, 3) unit, t (M,) s) at arc lengths ``a`` (m, clipped to the track)."""
        a = np.clip(np.asarray(a, dtype=np.float64), self.arc[0], self.arc[-1])
        i = np.clip(np.searchsorted(self.arc, a, side="right") - 1, 0, len(self.arc) - 2)
        da = self.arc[i + 1] - self.arc[i]
        f = np.where(da > 0, (a - self.arc[i]) / np.where(da > 0, da, 1.0), 0.0)
        v = self.axis[i] + (self.axis[i + 1] - self.axis[i]) * f[:, None]
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        return v, self.t[i] + (self.t[i + 1] - self.t[i]) * f

    def arc_at(self, distance: FloatArray) -> FloatArray:
        """Arc length (m) at chainages ``distance`` (m of distance_m)."""
        return np.interp(distance, self.distance, self.arc)

    def distance_at(self, arc: FloatArray) -> FloatArray:
        """Chainage (m of distance_m) at arc lengths ``arc`` (m)."""
        return np.interp(arc, self.arc, self.distance)

    def sigma_at(self, arc: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(sigma_h, sigma_v) m at arc lengths ``arc`` (m)."""
        return np.interp(arc, self.arc, self.sigma_h), np.interp(arc, self.arc, self.sigma_v)

    def position_at(self, arc: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(lat rad, lon rad, h m) at arc lengths ``arc`` (m)."""
        return (np.interp(arc, self.arc, self.lat), np.interp(arc, self.arc, self.lon),
                np.interp(arc, self.arc, self.h))  # fmt: skip


def axis_track(traj: Trajectory, step: float = TRACK_STEP_M) -> AxisTrack:
    """The pipe axis of a smoothed trajectory every ``step`` m of chainage (see the module).

    Built batched.BATCH points at a time: at 100 km the track has 5 million points, and the
    whole trajectory interpolated onto it at once took 1.7 GB of temporaries."""
    if len(traj.t) < 2:
        raise ValueError("a curvature profile needs a trajectory of at least two samples")
    times = chainage_times(traj.t, traj.distance, step)
    n = len(times)
    if n < 2:
        raise ValueError("the run covers less than one chainage step: no curvature profile")
    t, distance, lat, lon, h, sigma_h, sigma_v = (np.empty(n) for _ in range(7))
    axis = np.empty((n, 3))
    for b in range(0, n, batched.BATCH):
        s = slice(b, b + batched.BATCH)
        p = interpolate_trajectory(traj, times[s])
        t[s], distance[s], lat[s], lon[s], h[s] = p.t, p.distance, p.lat, p.lon, p.h
        a = body_x_axis(np.asarray(p.quat_nb).reshape(-1, 4))
        axis[s] = a / np.linalg.norm(a, axis=1, keepdims=True)
        sig = (np.full((len(a), 3), np.nan) if p.sigma_enu is None
               else np.asarray(p.sigma_enu, dtype=np.float64).reshape(-1, 3))  # fmt: skip
        sigma_h[s], sigma_v[s] = np.hypot(sig[:, 0], sig[:, 1]), sig[:, 2]
    del times, p, a, sig
    lon_u = unwrapped_lon(lon)
    steps = np.empty(n - 1)  # m, from each point to the next
    for b in range(1, n, batched.BATCH):
        e = min(b + batched.BATCH, n)
        j, i = slice(b, e), slice(b - 1, e - 1)  # the steps' last and first points
        rm, rn = radii(lat[j])
        d_n = (lat[j] - lat[i]) * (rm + h[j])
        d_e = (lon_u[j] - lon_u[i]) * (rn + h[j]) * np.cos(lat[j])
        d_u = h[j] - h[i]
        steps[i] = np.sqrt(d_n**2 + d_e**2 + d_u**2)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    return AxisTrack(np.maximum.accumulate(distance), arc, t, lat, lon, h, axis, sigma_h,
                     sigma_v)  # fmt: skip


def relative_angle_sigma(spec: ImuSpec, duration: FloatArray, angle: FloatArray) -> FloatArray:
    """One-sigma error (rad) of the change of the pipe axis over ``duration`` s through an
    ``angle`` rad turn, from the IMU noise model: angle random walk, bias instability over the
    duration, the angle quantum at both ends, the scale factor and misalignment times the turn."""
    d = np.maximum(np.asarray(duration, dtype=np.float64), 0.0)
    a = np.abs(np.asarray(angle, dtype=np.float64))
    var = (spec.gyro_arw**2 * d + (spec.gyro_bias_instability * d) ** 2
           + 2.0 * spec.gyro_quantization**2
           + ((spec.gyro_scale_factor + spec.gyro_misalignment) * a) ** 2)  # fmt: skip
    return np.sqrt(var)


@dataclass(frozen=True)
class CurvatureProfile:
    """Curvature on a regular chainage grid (one row per ``spacing`` m of distance_m).

    distance: (N,) m; t: (N,) s; lat, lon: rad; alt: m ellipsoidal; vertical, horizontal: 1/m
    (signs as in the module docstring); total: 1/m, >= 0; plane: rad in [0, 2 pi), clockwise
    from the top looking downstream (0 = curving upward, pi/2 = to the right); sigma: 1/m,
    one-sigma of ``total``; window: m of arc the values are averaged over; pitch, azimuth: rad
    of the axis at each row.
    """

    distance: FloatArray
    t: FloatArray
    lat: FloatArray
    lon: FloatArray
    alt: FloatArray
    vertical: FloatArray
    horizontal: FloatArray
    total: FloatArray
    plane: FloatArray
    sigma: FloatArray
    window: float
    pitch: FloatArray
    azimuth: FloatArray

    def __len__(self) -> int:
        return len(self.distance)


def windowed_curvature(
    track: AxisTrack, arc: FloatArray, window: float | FloatArray, spec: ImuSpec
) -> dict[str, FloatArray]:
    """Mean curvature over ``window`` m of arc (one for all, or one per point) centred on each
    of ``arc`` (m): its components (1/m), plane (rad), sigma (1/m) and the axis's pitch and
    azimuth (rad). Near the ends of the track the window shrinks to what the track holds."""
    lo = np.maximum(arc - 0.5 * window, track.arc[0])
    hi = np.minimum(arc + 0.5 * window, track.arc[-1])
    t0, time0 = track.at_arc(lo)
    t1, time1 = track.at_arc(hi)
    w = np.maximum(hi - lo, 1e-9)
    chord = t1 - t0
    turn = 2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(chord, axis=1), 0.0, 1.0))
    mid = t0 + t1
    mid /= np.maximum(np.linalg.norm(mid, axis=1, keepdims=True), 1e-12)
    pitch = np.arcsin(np.clip(mid[:, 2], -1.0, 1.0))
    az = np.arctan2(mid[:, 0], mid[:, 1])
    sp, cp, sa, ca = np.sin(pitch), np.cos(pitch), np.sin(az), np.cos(az)
    up = np.stack([-sp * sa, -sp * ca, cp], axis=1)  # perpendicular to the axis, upward
    right = np.stack([ca, -sa, np.zeros_like(ca)], axis=1)  # horizontal, to the right
    norm = np.linalg.norm(chord, axis=1)
    scale = np.where(norm > 1e-15, turn / np.maximum(norm, 1e-15), 1.0) / w
    vertical = np.einsum("ij,ij->i", chord, up) * scale
    horizontal = np.einsum("ij,ij->i", chord, right) * scale
    total = turn / w
    plane = np.mod(np.arctan2(horizontal, vertical), 2.0 * math.pi)
    sigma = relative_angle_sigma(spec, time1 - time0, turn) / w
    return {"vertical": vertical, "horizontal": horizontal, "total": total, "plane": plane,
            "sigma": sigma, "pitch": pitch, "azimuth": az}  # fmt: skip


def curvature_profile(
    traj: Trajectory,
    spec: ImuSpec,
    *,
    window: float,
    spacing: float = 0.5,
    track: AxisTrack | None = None,
) -> CurvatureProfile:
    """The curvature of a smoothed trajectory every ``spacing`` m of chainage, averaged over
    ``window`` m (see the module); ``spec`` is the IMU noise model of the smoothing (sigmas)."""
    if not (math.isfinite(window) and window > 0):
        raise ValueError(f"the curvature window must be a positive number of metres, not {window}")
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"the chainage spacing must be a positive number of metres, not {spacing}")
    track = track or axis_track(traj, min(TRACK_STEP_M, window / 8.0))
    first = math.ceil(track.distance[0] / spacing - 1e-9)
    last = math.floor(track.distance[-1] / spacing + 1e-9)
    distance = np.arange(first, last + 1, dtype=np.float64) * spacing
    arc = track.arc_at(distance)
    values = windowed_curvature(track, arc, window, spec)
    lat, lon, alt = track.position_at(arc)
    _, t = track.at_arc(arc)
    return CurvatureProfile(distance=distance, t=t, lat=lat, lon=lon, alt=alt, window=window,
                            **values)  # fmt: skip
