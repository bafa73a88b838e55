"""Initial alignment and heading anchoring.

- :func:`level`: roll and pitch from the mean specific force at rest (seed 001 eq. 11-12 in
  base_link FLU axes);
- :func:`gyro_bias_at_rest`: gyro bias = mean rate minus the Earth rate seen in the body;
- :func:`marker_bearing`: azimuth from the first to the second marker (seed 000);
- :func:`mag_azimuth`: azimuth from a levelled magnetometer reading and the declination;
- :func:`reanchor_heading`: rotate the current state about the vertical through a pivot so that
  the dead-reckoned displacement since the first marker points at the second marker.
All angles rad; azimuth clockwise from true north.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import attitude as att
from . import earth
from .state import NavState
from .types import Marker

Array = NDArray[np.float64]


def level(f_mean_b: Array) -> tuple[float, float]:
    """(roll, pitch) rad from the mean specific force (m/s^2, base_link) of a pig at rest."""
    f = np.asarray(f_mean_b, dtype=np.float64)
    pitch = float(np.arctan2(f[0], np.hypot(f[1], f[2])))
    roll = float(np.arctan2(f[1], f[2]))
    return roll, pitch


def gyro_bias_at_rest(
    gyro_mean_b: Array, c_nb: Array, lat: float, earth_sign: float = 1.0
) -> Array:
    """Gyro bias (rad/s, base_link) from the mean rate at rest and the attitude C_nb
    (earth_sign -1 for time-reversed data)."""
    w_ie = earth_sign * earth.earth_rate_n(lat)
    return np.asarray(gyro_mean_b, dtype=np.float64) - c_nb.T @ w_ie


def enu_of(marker: Marker, ref: Marker) -> Array:
    """ENU position (m) of marker relative to ref."""
    return earth.geodetic_to_enu(marker.lat, marker.lon, marker.alt, ref.lat, ref.lon, ref.alt)


def marker_bearing(first: Marker, second: Marker) -> tuple[float, float]:
    """(azimuth rad, horizontal distance m) from the first marker to the second."""
    d = enu_of(second, first)
    return float(np.mod(np.arctan2(d[0], d[1]), 2 * np.pi)), float(np.hypot(d[0], d[1]))


def mag_azimuth(field_b: Array, roll: float, pitch: float, declination: float) -> float:
    """Azimuth (rad) of base_link x from a magnetometer reading (base_link) at known roll/pitch."""
    c0 = att.dcm_from_euler(roll, pitch, 0.0)
    m = c0 @ np.asarray(field_b, dtype=np.float64)
    az_field = np.arctan2(m[0], m[1])
    return float(np.mod(declination - az_field, 2 * np.pi))


def reanchor_heading(s: NavState, pivot: Marker, target: Marker) -> tuple[NavState, float]:
    """Rotate s about the vertical through ``pivot`` so that its horizontal displacement from
    ``pivot`` points at ``target``; returns the new state and the rotation (rad, azimuth
    increase). Position, velocity and attitude rotate together; biases are body-frame and stay.
    """
    here = earth.geodetic_to_enu(s.lat, s.lon, s.h, pivot.lat, pivot.lon, pivot.alt)
    goal = enu_of(target, pivot)
    if np.hypot(here[0], here[1]) < 1e-3 or np.hypot(goal[0], goal[1]) < 1e-3:
        return s, 0.0
    d_az = float(
        np.angle(np.exp(1j * (np.arctan2(goal[0], goal[1]) - np.arctan2(here[0], here[1]))))
    )
    rz = att.dcm_from_rotvec(np.array([0.0, 0.0, -d_az]))  # azimuth increase = rotation about -U
    new = s.copy()
    p = rz @ here
    lat, lon, h = earth.enu_to_geodetic(p, pivot.lat, pivot.lon, pivot.alt)
    new.lat, new.lon, new.h = float(lat), float(lon), float(h)
    new.vel_n = rz @ s.vel_n
    new.q_nb = att.quat_normalize(att.quat_mul(att.quat_from_rotvec([0.0, 0.0, -d_az]), s.q_nb))
    return new, d_az
