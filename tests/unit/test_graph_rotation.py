"""The graph smoother's exact rotation step: rotate_about turns a trajectory rigidly about the
vertical through a pivot, and retract applies a step's turn of the initial heading that way."""

import math

import numpy as np
from pipe_nav_core.filter.anchoring import FreeHeading
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.graph.rotation import retract, rotate_about
from pipe_nav_core.model.state import (
    SV_H,
    SV_LAT,
    SV_LON,
    SV_Q,
    SV_SIZE,
    SV_VEL,
    Layout,
    difference_many,
    inject_many,
)

PIVOT = (math.radians(30.5), math.radians(114.3), 25.0)


def _track(K: int = 50) -> np.ndarray:
    """Flat states along a 100 m straight line heading 62 degrees, sloping down 2 %."""
    X = np.zeros((K, SV_SIZE))
    s = np.linspace(0.0, 100.0, K)
    az = math.radians(62.0)
    enu = np.stack([s * math.sin(az), s * math.cos(az), -0.02 * s], axis=1) + [3.0, -2.0, 0.5]
    lat, lon, h = earth.enu_to_geodetic(enu, *PIVOT)
    X[:, SV_LAT], X[:, SV_LON], X[:, SV_H] = lat, lon, h
    X[:, SV_VEL] = np.array([math.sin(az), math.cos(az), -0.02])
    X[:, SV_Q] = att.quat_from_euler(0.01, -0.02, az)
    return X


def _enu(X: np.ndarray) -> np.ndarray:
    return earth.geodetic_to_enu(X[:, SV_LAT], X[:, SV_LON], X[:, SV_H], *PIVOT)


def test_rotate_about_is_rigid_and_turns_the_heading() -> None:
    X = _track()
    angle = math.radians(30.0)
    Y = rotate_about(X, PIVOT, angle)
    a, b = _enu(X), _enu(Y)
    assert np.allclose(np.hypot(a[:, 0], a[:, 1]), np.hypot(b[:, 0], b[:, 1]), atol=1e-6)
    assert np.allclose(a[:, 2], b[:, 2], atol=1e-6)
    turn = np.arctan2(b[:, 1], b[:, 0]) - np.arctan2(a[:, 1], a[:, 0])
    assert np.allclose(np.angle(np.exp(1j * turn)), angle, atol=1e-9)
    az_x = att.euler_from_dcm(att.dcm_from_quat(X[:, SV_Q]))[2]
    az_y = att.euler_from_dcm(att.dcm_from_quat(Y[:, SV_Q]))[2]
    # counter-clockwise about up: the azimuth (clockwise from north) falls by the angle
    assert np.allclose(np.angle(np.exp(1j * (az_x - az_y))), angle, atol=1e-9)
    assert np.allclose(np.linalg.norm(Y[:, SV_VEL], axis=1), np.linalg.norm(X[:, SV_VEL], axis=1))


def test_retract_applies_the_heading_turn_exactly() -> None:
    """A step that is a pure turn of the heading (theta times its error-state direction)
    lands on the exactly rotated trajectory; its linearization (inject) misses it by the
    turn's second order; a step without a turn is the plain injection."""
    lay = Layout("ins")
    X = _track()
    theta = math.radians(30.0)
    g = FreeHeading(0.0, *PIVOT).direction(X[:, SV_LAT], X[:, SV_LON], X[:, SV_H],
                                           X[:, SV_VEL], lay)  # fmt: skip
    exact = rotate_about(X, PIVOT, theta)
    got = retract(X, theta * g, lay, PIVOT)
    assert np.abs(difference_many(got, exact, lay)).max() < 1e-6
    linear = inject_many(X, theta * g, lay)
    assert np.abs(_enu(linear) - _enu(exact)).max() > 5.0  # m: the tangent misses the arc
    d = np.zeros((len(X), lay.n))
    d[:, lay.pos] = 0.1
    assert np.array_equal(retract(X, d, lay, PIVOT), inject_many(X, d, lay))
    assert np.array_equal(retract(X, theta * g, lay, None), linear)
