"""Self-test of the simulator's IMU: error-free data integrated by an independent, careful
strapdown integrator from the true initial state must reproduce the true trajectory.

The reference integrator here shares nothing with the simulator but the Earth model:
- each sample is treated as the MEAN over the interval since the previous one (INTERFACES.md);
  within an interval the rate and the specific force are reconstructed as the quadratic whose
  means over the previous, current and next interval match the samples;
- the body attitude increment and the velocity increment (in the body frame at the interval's
  start: rotation and sculling in full) are integrated with RK4 sub-steps, vectorized over all
  intervals (that is the coning and sculling correction, to high order);
- the navigation frame (ENU) turns at Earth rate plus transport rate; velocity gets normal
  gravity and Coriolis; latitude, longitude and height are integrated with the WGS84 radii.
  The weak coupling of these terms to the trajectory is resolved by a few fixed-point passes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.model.sensors import imu_grade
from pipe_nav_core.sim import Bend, RollTurn, Sag, Scenario, Stop, simulate
from pipe_nav_core.types import ImuSamples

DEG = math.pi / 180.0


def _quadratic(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients of p(x) = a + b x + c x^2 (x in [-1/2, 1/2] over each interval) whose means
    over the neighbouring intervals equal the samples."""
    prev = np.vstack([m[:1], m[:-1]])
    nxt = np.vstack([m[1:], m[-1:]])
    b = 0.5 * (nxt - prev)
    c = 0.5 * (prev + nxt - 2.0 * m)
    a = m - c / 12.0
    return a, b, c


def _body_increments(
    t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, substeps: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Per interval k (t[k-1], t[k]]: rotation q_{b(k-1) b(k)} and velocity increment resolved
    in b(k-1), by RK4 on the reconstructed signals."""
    dt = np.diff(t)[:, None]
    ga, gb, gc = (x[1:] for x in _quadratic(gyro))
    fa, fb, fc = (x[1:] for x in _quadratic(accel))
    n = len(dt)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    u = np.zeros((n, 3))
    h = dt / substeps

    def deriv(tau: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = tau / dt - 0.5
        w = ga + gb * x + gc * x * x
        f = fa + fb * x + fc * x * x
        dq = 0.5 * att.quat_mul(q, np.hstack([w, np.zeros((n, 1))]))
        du = np.einsum("nij,nj->ni", att.dcm_from_quat(q), f)
        return dq, du

    tau = np.zeros((n, 1))
    for _ in range(substeps):
        k1q, k1u = deriv(tau, q)
        k2q, k2u = deriv(tau + h / 2, q + h / 2 * k1q)
        k3q, k3u = deriv(tau + h / 2, q + h / 2 * k2q)
        k4q, k4u = deriv(tau + h, q + h * k3q)
        q = q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
        u = u + h / 6 * (k1u + 2 * k2u + 2 * k3u + k4u)
        tau = tau + h
    return q / np.linalg.norm(q, axis=1, keepdims=True), u


def strapdown(
    imu: ImuSamples,
    q0: np.ndarray,
    v0: np.ndarray,
    lat0: float,
    lon0: float,
    h0: float,
    *,
    earth_rate: bool = True,
    passes: int = 5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference strapdown integration. Returns positions (N, 3) [lat rad, lon rad, h m], ENU
    velocities (N, 3) m/s and q_nb (N, 4) at the sample times, the first being the given
    initial state."""
    t = imu.t
    dt = np.diff(t)
    dq, dv_body = _body_increments(t, imu.gyro, imu.accel)
    right = att.quat_cumprod(q0, dq)  # q0 * dq_1 * ... * dq_k
    n = len(t)
    lat = np.full(n, lat0)
    lon = np.full(n, lon0)
    h = np.full(n, h0)
    v = np.tile(v0, (n, 1))
    q = np.tile(q0, (n, 1))
    for _ in range(passes):
        lat_m = 0.5 * (lat[1:] + lat[:-1])
        h_m = 0.5 * (h[1:] + h[:-1])
        v_m = 0.5 * (v[1:] + v[:-1])
        w_ie = earth.earth_rate_n(lat_m) * (1.0 if earth_rate else 0.0)
        w_en = earth.transport_rate_n(lat_m, h_m, v_m)
        zeta = (w_ie + w_en) * dt[:, None]
        # the navigation frame turns by zeta each step: q_nb(k) = q_n(k)n(0) q0 dq_1 ... dq_k
        left = att.quat_conj(att.quat_cumprod([0.0, 0.0, 0.0, 1.0], att.quat_from_rotvec(zeta)))
        q = np.vstack([q0[None, :], att.quat_mul(left, right)])
        dv = np.einsum("nij,nj->ni", att.dcm_from_quat(q[:-1]), dv_body)
        dv = dv - 0.5 * np.cross(zeta, dv)
        dv = dv + (earth.gravity_n(lat_m, h_m) - np.cross(2.0 * w_ie + w_en, v_m)) * dt[:, None]
        v = np.vstack([v0[None, :], v0 + np.cumsum(dv, axis=0)])
        v_m = 0.5 * (v[1:] + v[:-1])
        rm, rn = earth.radii(lat_m)
        h = h0 + np.concatenate([[0.0], np.cumsum(v_m[:, 2] * dt)])
        lat = lat0 + np.concatenate([[0.0], np.cumsum(v_m[:, 1] * dt / (rm + h_m))])
        dlon = v_m[:, 0] * dt / ((rn + h_m) * np.cos(lat_m))
        lon = lon0 + np.concatenate([[0.0], np.cumsum(dlon)])
    return np.stack([lat, lon, h], axis=1), v, q


def selftest_scenario() -> Scenario:
    """About 100 s: two tight horizontal bends, grade changes, a sag, a stop and a full roll
    turn at 2.5 rad/s; error-free IMU, ideal odometer, no magnetometer."""
    d = 0.2
    return Scenario(
        name="selftest",
        lat=50.0 * DEG,
        lon=10.0 * DEG,
        alt=300.0,
        azimuth=30.0 * DEG,
        length=90.0,
        pipe_diameter=d,
        features=(
            Bend(15.0, 90.0 * DEG, 3.0 * d, "h"),
            Bend(30.0, 5.0 * DEG, 2.0, "v"),
            Bend(40.0, -5.0 * DEG, 2.0, "v"),
            Sag(50.0, 20.0, 0.3, "v"),
            Bend(75.0, -45.0 * DEG, 1.5 * d, "h"),
        ),
        speed=1.0,
        static_start=3.0,
        static_end=3.0,
        roll0=0.3,
        roll_turns=(RollTurn(60.0, 1.0, 2.5),),
        stops=(Stop(45.0, 3.0),),
        imu_spec=imu_grade("industrial").scaled(0.0),
        mag_enabled=False,
        odo_tick=0.0,
        odo_scale_sigma=0.0,
        odo_slip_interval=0.0,
    )


@pytest.fixture(scope="module")
def run():
    return simulate(selftest_scenario(), seed=3)


def _errors(run, pos: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tr = run.truth
    rm, rn = earth.radii(tr.lat)
    dn = (pos[:, 0] - tr.lat) * (rm + tr.h)
    de = (pos[:, 1] - tr.lon) * (rn + tr.h) * np.cos(tr.lat)
    du = pos[:, 2] - tr.h
    dq = att.quat_mul(att.quat_conj(tr.quat_nb), q)
    return np.sqrt(de**2 + dn**2 + du**2), np.linalg.norm(att.rotvec_from_quat(dq), axis=1)


def test_scenario_is_demanding(run):
    tr = run.truth
    assert 95.0 < tr.t[-1] - tr.t[0] < 120.0
    assert np.max(np.abs(run.log.imu.gyro[:, 0])) > 2.4  # the roll turn
    assert np.max(np.abs(run.log.imu.gyro[:, 2])) > 1.5  # tight horizontal bends
    roll, pitch, az = att.euler_from_dcm(att.dcm_from_quat(tr.quat_nb))
    assert np.max(np.unwrap(roll)) - np.min(np.unwrap(roll)) > 2 * np.pi - 0.1
    assert np.ptp(pitch) > 4.0 * DEG
    assert np.ptp(tr.h) > 0.3


def test_error_free_imu_reproduces_truth(run):
    tr = run.truth
    pos, vel, q = strapdown(
        run.log.imu, tr.quat_nb[0], tr.vel_n[0], tr.lat[0], tr.lon[0], tr.h[0]
    )
    pos_err, att_err = _errors(run, pos, q)
    assert pos_err.max() < 5e-3, f"position error {pos_err.max():.2e} m"
    assert att_err.max() < 1e-5, f"attitude error {att_err.max():.2e} rad"
    assert np.abs(vel - tr.vel_n).max() < 1e-4


def test_reference_integrator_detects_a_missing_earth_rate(run):
    # The same data integrated without the Earth's rotation must go visibly wrong: the test
    # above therefore really checks the Earth-rate and Coriolis content of the simulated IMU.
    tr = run.truth
    pos, _, q = strapdown(
        run.log.imu, tr.quat_nb[0], tr.vel_n[0], tr.lat[0], tr.lon[0], tr.h[0], earth_rate=False
    )
    pos_err, att_err = _errors(run, pos, q)
    assert pos_err.max() > 0.1
    assert att_err.max() > 1e-3


def test_point_sampling_is_not_what_the_simulator_delivers(run):
    # The samples are interval means: at a 2.5 rad/s roll turn the mean rate differs from the
    # rate at the stamp by about half an interval's change; check against the exact kinematics.
    from pipe_nav_core.sim.kinematics import evaluate

    t = run.log.imu.t
    dt = t[1] - t[0]
    i = int(np.argmax(np.abs(np.diff(run.log.imu.gyro[:, 0]))))
    ts = np.array([t[i] - dt, t[i]])
    point = evaluate(run.geometry, run.motion, ts).omega_ib_b()
    mean = run.log.imu.gyro[i]
    assert abs(mean[0] - point[1, 0]) > 1e-4
    assert abs(mean[0] - 0.5 * (point[0, 0] + point[1, 0])) < abs(mean[0] - point[1, 0])
