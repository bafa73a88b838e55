"""Rotations (geo/attitude.py): Euler angles, quaternion products, matrices, against scipy."""

import math

import numpy as np
from pipe_nav_core.geo import attitude as att


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


def test_the_body_x_axis_is_the_matrixs_first_column_bit_for_bit():
    rng = np.random.default_rng(5)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x = att.body_x_axis(q)
    assert x.tobytes() == np.ascontiguousarray(att.dcm_from_quat(q)[:, :, 0]).tobytes()
    assert att.body_x_axis(q[7]).tobytes() == att.dcm_from_quat(q[7])[:, 0].tobytes()


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
