"""WGS84 Earth model: radii, normal gravity, Earth and transport rates, coordinate conversions.

Navigation frame n is local East-North-Up. Latitude and longitude in radians, heights in metres
above the WGS84 ellipsoid. Functions accept scalars or numpy arrays (broadcasting); a float
latitude (and height) takes a scalar ``math`` path, as the filter calls them once per epoch.
"""

from __future__ import annotations

import math

import numpy as np
import pymap3d
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.jit import kernel

A = 6378137.0  # m, semi-major axis
F = 1.0 / 298.257223563
E2 = F * (2.0 - F)  # first eccentricity squared
B = A * (1.0 - F)
OMEGA_IE = 7.292115e-5  # rad/s, Earth rotation rate
GM = 3.986004418e14  # m^3/s^2
# Somigliana normal gravity constants
GAMMA_E = 9.7803253359  # m/s^2 at the equator
GAMMA_K = 0.00193185265241
M_RATIO = OMEGA_IE**2 * A**2 * B / GM

Array = NDArray[np.float64]


@kernel
def _radii(lat):  # noqa: ANN001, ANN202 (float or array: numba specializes)
    s = np.sin(lat)
    w = np.sqrt(1.0 - E2 * (s * s))
    return A * (1.0 - E2) / (w * w * w), A / w


@kernel
def _gravity(lat, h):  # noqa: ANN001, ANN202
    s = np.sin(lat)
    s2 = s * s
    g0 = GAMMA_E * (1.0 + GAMMA_K * s2) / np.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 / A * (1.0 + F + M_RATIO - 2.0 * F * s2) * h + 3.0 / A**2 * (h * h))


@kernel
def earth_rate_k(lat: float, sign: float = 1.0) -> Array:
    """Earth rotation rate omega_ie in ENU (rad/s, (3,)) at latitude lat (rad); sign -1 for
    time-reversed data."""
    return np.array([0.0, sign * OMEGA_IE * np.cos(lat), sign * OMEGA_IE * np.sin(lat)])


@kernel
def transport_rate_k(lat: float, h: float, ve: float, vn: float) -> Array:
    """Transport rate omega_en in ENU (rad/s, (3,)) at lat (rad), h (m) for east and north
    velocity ve, vn (m/s)."""
    rm, rn = _radii(lat)
    return np.array([-vn / (rm + h), ve / (rn + h), ve * np.tan(lat) / (rn + h)])


def _f(x: ArrayLike) -> float | Array:
    return x if isinstance(x, float) else np.asarray(x, dtype=np.float64)


def radii(lat: ArrayLike) -> tuple[Array, Array]:
    """Meridian radius R_M and prime-vertical radius R_N (m) at geodetic latitude lat (rad).
    Compiled (:func:`_radii`), so that the numba kernels share it."""
    return _radii(_f(lat))


def gravity(lat: ArrayLike, h: ArrayLike) -> Array:
    """Magnitude of normal gravity (m/s^2) at latitude lat (rad) and height h (m) (Somigliana
    with the second-order free-air correction). Gravity points down (-U) in ENU. Compiled
    (:func:`_gravity`), so that the numba kernels share it."""
    lat, h = _f(lat), _f(h)
    if isinstance(lat, float) != isinstance(h, float):  # one array: both arrays, same shape
        lat, h = lat + np.zeros(np.shape(h)), h + np.zeros(np.shape(lat))
    return _gravity(lat, h)


def gravity_n(lat: ArrayLike, h: ArrayLike) -> Array:
    """Normal gravity vector in ENU (m/s^2), shape (..., 3)."""
    g = gravity(lat, h)
    if isinstance(g, float):
        return np.array([0.0, 0.0, -g])
    z = np.zeros_like(g)
    return np.stack([z, z, -g], axis=-1)


def earth_rate_n(lat: ArrayLike) -> Array:
    """Earth rotation rate omega_ie in ENU (rad/s), shape (..., 3)."""
    if isinstance(lat, float):
        return earth_rate_k(lat)
    lat = np.asarray(lat, dtype=np.float64)
    return np.stack([np.zeros_like(lat), OMEGA_IE * np.cos(lat), OMEGA_IE * np.sin(lat)], axis=-1)


def transport_rate_n(lat: ArrayLike, h: ArrayLike, vel_n: ArrayLike) -> Array:
    """Transport rate omega_en in ENU (rad/s) for ENU velocity vel_n (m/s), shape (..., 3)."""
    v = np.asarray(vel_n, dtype=np.float64)
    if isinstance(lat, float) and isinstance(h, float) and v.ndim == 1:
        return transport_rate_k(lat, h, float(v[0]), float(v[1]))
    rm, rn = radii(lat)
    ve, vn = v[..., 0], v[..., 1]
    return np.stack([-vn / (rm + h), ve / (rn + h), ve * np.tan(lat) / (rn + h)], axis=-1)


def enu_to_geodetic_increment(
    d_enu: ArrayLike, lat: ArrayLike, h: ArrayLike
) -> tuple[Array, Array, Array]:
    """Small ENU displacement (m) -> (dlat rad, dlon rad, dh m) at latitude lat, height h."""
    d = np.asarray(d_enu, dtype=np.float64)
    rm, rn = radii(lat)
    if isinstance(lat, float) and isinstance(h, float) and d.ndim == 1:
        e, n, u = d.tolist()
        return n / (rm + h), e / ((rn + h) * math.cos(lat)), u
    return d[..., 1] / (rm + h), d[..., 0] / ((rn + h) * np.cos(lat)), d[..., 2]


def unwrapped_lon(lon: ArrayLike) -> Array:
    """Longitudes (rad, in sample order) made continuous across +-180 deg (np.unwrap's
    values); the array itself where no step crosses it (there np.unwrap only adds exact
    zeros, at a pass over the samples)."""
    lon = np.asarray(lon, dtype=np.float64)
    return np.unwrap(lon) if np.any(np.abs(np.diff(lon)) >= np.pi) else lon


def geodetic_to_ecef(lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> Array:
    """WGS84 geodetic (rad, rad, m) -> ECEF (m), shape (..., 3)."""
    x, y, z = pymap3d.geodetic2ecef(lat, lon, h, deg=False)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1).astype(np.float64)


def ecef_to_geodetic(xyz: ArrayLike) -> tuple[Array, Array, Array]:
    """ECEF (m) -> WGS84 geodetic (lat rad, lon rad, h m)."""
    p = np.asarray(xyz, dtype=np.float64)
    lat, lon, h = pymap3d.ecef2geodetic(p[..., 0], p[..., 1], p[..., 2], deg=False)
    return np.asarray(lat), np.asarray(lon), np.asarray(h)


def geodetic_to_enu(
    lat: ArrayLike, lon: ArrayLike, h: ArrayLike, lat0: float, lon0: float, h0: float
) -> Array:
    """Geodetic (rad, rad, m) -> ENU (m) in the tangent plane at the datum (lat0, lon0, h0)."""
    e, n, u = pymap3d.geodetic2enu(lat, lon, h, lat0, lon0, h0, deg=False)
    return np.stack(np.broadcast_arrays(e, n, u), axis=-1).astype(np.float64)


def enu_to_geodetic(
    enu: ArrayLike, lat0: float, lon0: float, h0: float
) -> tuple[Array, Array, Array]:
    """ENU (m) at the datum (lat0, lon0, h0) -> geodetic (lat rad, lon rad, h m)."""
    p = np.asarray(enu, dtype=np.float64)
    lat, lon, h = pymap3d.enu2geodetic(p[..., 0], p[..., 1], p[..., 2], lat0, lon0, h0, deg=False)
    return np.asarray(lat), np.asarray(lon), np.asarray(h)
