"""The WGS84 Earth model (geo/earth.py): gravity, radii, ENU conversions."""

import math

import numpy as np
import pytest
from pipe_nav_core.geo import earth


def test_gravity_and_radii_known_values():
    # Normal gravity: 9.7803 at the equator, 9.8322 at the poles (WGS84).
    assert earth.gravity(0.0, 0.0) == pytest.approx(9.7803253359, abs=1e-9)
    assert earth.gravity(math.pi / 2, 0.0) == pytest.approx(9.8321849378, abs=1e-7)
    # Free-air gradient about -3.086e-6 m/s^2 per m.
    assert earth.gravity(0.7, 1000.0) - earth.gravity(0.7, 0.0) == pytest.approx(
        -3.086e-3, rel=2e-3
    )
    rm, rn = earth.radii(0.0)
    assert rn == pytest.approx(earth.A)
    assert rm == pytest.approx(earth.A * (1 - earth.E2))


def test_enu_round_trip_and_increment():
    lat0, lon0, h0 = math.radians(39.9), math.radians(116.4), 50.0
    enu = np.array([[100.0, -250.0, 3.0], [1.0, 2.0, -1.0]])
    lat, lon, h = earth.enu_to_geodetic(enu, lat0, lon0, h0)
    back = earth.geodetic_to_enu(lat, lon, h, lat0, lon0, h0)
    np.testing.assert_allclose(back, enu, atol=1e-6)
    dlat, dlon, dh = earth.enu_to_geodetic_increment(np.array([1.0, 1.0, 0.0]), lat0, h0)
    e = earth.geodetic_to_enu(lat0 + dlat, lon0 + dlon, h0 + dh, lat0, lon0, h0)
    np.testing.assert_allclose(e, [1.0, 1.0, 0.0], atol=1e-6)
