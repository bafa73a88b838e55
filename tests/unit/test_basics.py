import math

import numpy as np
import pytest
from pipe_nav_core.config import ConfigError, NavConfig
from pipe_nav_core.geo import attitude as att
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


def test_euler_round_trip_and_meaning():
    rng = np.random.default_rng(1)
    roll = rng.uniform(-3, 3, 50)
    pitch = rng.uniform(-1.5, 1.5, 50)
    az = rng.uniform(0, 2 * np.pi, 50)
    c = att.dcm_from_euler(roll, pitch, az)
    r2, p2, a2 = att.euler_from_dcm(c)
    np.testing.assert_allclose(r2, roll, atol=1e-9)
    np.testing.assert_allclose(p2, pitch, atol=1e-9)
    np.testing.assert_allclose(a2, az, atol=1e-9)
    # Azimuth 90 deg, pitch +10 deg: nose points east and up.
    x = att.dcm_from_euler(0.0, math.radians(10), math.radians(90))[:, 0]
    np.testing.assert_allclose(
        x, [math.cos(math.radians(10)), 0, math.sin(math.radians(10))], atol=1e-12
    )


def test_quaternion_chain_matches_scipy():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2)
    rv = rng.normal(0, 0.3, (37, 3))
    q0 = att.quat_from_rotvec([0.1, -0.2, 0.3])
    chain = att.quat_cumprod(q0, att.quat_from_rotvec(rv))
    r = Rotation.from_quat(q0)
    for i in range(len(rv)):
        r = r * Rotation.from_rotvec(rv[i])
        np.testing.assert_allclose(att.dcm_from_quat(chain[i]), r.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(att.rotvec_from_quat(att.quat_from_rotvec(rv)), rv, atol=1e-12)


def test_quaternion_of_a_matrix_equals_scipys_bit_for_bit():
    from scipy.spatial.transform import Rotation

    r = Rotation.random(5000, random_state=3)
    m = r.as_matrix()
    m[:4] = [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
             np.diag([-1.0, -1.0, 1.0])]  # each branch at its edge (angles 0 and pi)
    got = att.quat_from_dcm(m)
    assert np.array_equal(got, att.quat_normalize(Rotation.from_matrix(m).as_quat()))
    assert np.array_equal(att.quat_from_dcm(m[7]), got[7])
    assert att.quat_from_dcm(m.reshape(50, 100, 3, 3)).shape == (50, 100, 4)


def test_config_from_dict_degrees_and_errors():
    cfg = NavConfig.from_dict({"initial_azimuth_deg": 90, "mode": "dr"})
    assert cfg.initial_azimuth == pytest.approx(math.pi / 2)
    with pytest.raises(ConfigError, match="mode"):
        NavConfig.from_dict({"mode": "magic"})
    with pytest.raises(ConfigError, match="unknown setting"):
        NavConfig.from_dict({"bogus": 1})
    with pytest.raises(ConfigError, match="zupt_sigma"):
        NavConfig.from_dict({"zupt_sigma": -1})
