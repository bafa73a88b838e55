"""The one strongly nonlinear direction of the batch problem: a rotation of the whole solution
about the vertical through the first marker (the initial heading, which only the marker
geometry fixes). A Gauss-Newton step along it is applied as that exact rotation rather than
as its linearization (positions moved along the tangent, velocities scaled by 1/cos): from
tens of degrees off, the linearized move leaves the trajectory off its own IMU and odometer
by the rotation's second order, and the step fails (:func:`retract`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.filter.anchoring import FreeHeading
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.model.state import SV_H, SV_LAT, SV_LON, SV_Q, SV_VEL, Layout, inject_many

Array = NDArray[np.float64]
Pivot = tuple[float, float, float]  # lat rad, lon rad, h m


def rotate_about(X: Array, pivot: Pivot, angle: float) -> Array:
    """Flat states X (K, SV_SIZE) turned by angle (rad, right-handed about the up axis:
    counter-clockwise seen from above, the azimuth decreases) about the vertical through pivot:
    positions (in the pivot's ENU plane), velocities and attitudes together; body-frame
    states unchanged."""
    out = np.array(X, dtype=np.float64)
    rz = att.dcm_from_rotvec(np.array([0.0, 0.0, angle]))
    lat0, lon0, h0 = pivot
    enu = earth.geodetic_to_enu(X[:, SV_LAT], X[:, SV_LON], X[:, SV_H], lat0, lon0, h0)
    lat, lon, h = earth.enu_to_geodetic(enu.reshape(-1, 3) @ rz.T, lat0, lon0, h0)
    out[:, SV_LAT], out[:, SV_LON], out[:, SV_H] = lat, lon, h
    out[:, SV_VEL] = X[:, SV_VEL] @ rz.T
    dq = np.broadcast_to(att.quat_from_rotvec(np.array([0.0, 0.0, angle])), (len(X), 4))
    out[:, SV_Q] = att.quat_normalize(att.quat_mul(dq, X[:, SV_Q]))
    return out


def retract(X: Array, delta: Array, layout: Layout, pivot: Pivot | None) -> Array:
    """X (+) delta (flat states (K, SV_SIZE), error states (K, n)), with the step's rotation of
    the initial heading, theta = delta[0, attitude up], applied as the exact rotation of the
    whole trajectory about pivot and only the rest of the step, delta - theta g (g: the error
    state of a unit rotation, :meth:`FreeHeading.direction`), injected, turned with the
    trajectory. Without a pivot (no marker) or a turn: X (+) delta."""
    theta = 0.0 if pivot is None else float(delta[0, layout.att.start + 2])
    if pivot is None or theta == 0.0:
        return inject_many(X, delta, layout)
    g = FreeHeading(0.0, *pivot).direction(
        X[:, SV_LAT], X[:, SV_LON], X[:, SV_H], X[:, SV_VEL], layout
    )
    rest = delta - theta * g
    rz = att.dcm_from_rotvec(np.array([0.0, 0.0, theta]))
    for sl in (layout.att, layout.vel, layout.pos):
        if sl is not None:
            rest[:, sl] = rest[:, sl] @ rz.T
    return inject_many(rotate_about(X, pivot, theta), rest, layout)
