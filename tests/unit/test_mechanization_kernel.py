"""The numba kernels of mechanization.py against the vectorized numpy implementation they
replaced (kept below as the reference): same results to round-off on random blocks."""

from __future__ import annotations

import numpy as np
import pytest
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.model.mechanization import BlockResult, Carry, dr_block, ins_block
from pipe_nav_core.model.state import NavState, odometer_axis

from pipe_nav_core import jit

# --- reference: the numpy implementation of mechanization.py before the numba kernels ---


def _ref_dcm(q):
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    c = np.empty((len(q), 3, 3))
    c[:, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    c[:, 0, 1] = 2.0 * (x * y - w * z)
    c[:, 0, 2] = 2.0 * (x * z + w * y)
    c[:, 1, 0] = 2.0 * (x * y + w * z)
    c[:, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    c[:, 1, 2] = 2.0 * (y * z - w * x)
    c[:, 2, 0] = 2.0 * (x * z - w * y)
    c[:, 2, 1] = 2.0 * (y * z + w * x)
    c[:, 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return c


def _ref_attitudes(s, t, gyro, carry, w_in):
    dt = np.diff(np.concatenate([[s.t], t]))
    rate = gyro - s.bg
    if np.any(s.gm):
        rate = np.linalg.solve(np.eye(3) + s.gm, rate.T).T
    dtheta = rate * dt[:, None]
    before = np.vstack([carry.dtheta[None, :], dtheta[:-1]])
    rv = dtheta + np.cross(before, dtheta) / 12.0  # two-sample coning correction
    q_body = att.quat_cumprod(s.q_nb, att.quat_from_rotvec(rv))
    q_nav = att.quat_from_rotvec(-np.outer(t - s.t, w_in))
    q = att.quat_mul(q_nav, q_body)
    return q, dtheta, dt


def _ref_specific_force(s, accel):
    f = accel - s.ba
    if np.any(s.am):
        f = np.linalg.solve(np.eye(3) + s.am, f.T).T
    return f


def _ref_ins_block(s, t, gyro, accel, carry, earth_sign=1.0):
    w_ie = earth_sign * earth.earth_rate_n(s.lat)
    w_en = earth.transport_rate_n(s.lat, s.h, s.vel_n)
    w_in = w_ie + w_en
    q, dtheta, dt = _ref_attitudes(s, t, gyro, carry, w_in)
    dvel = _ref_specific_force(s, accel) * dt[:, None]
    th_before = np.vstack([carry.dtheta[None, :], dtheta[:-1]])
    dv_before = np.vstack([carry.dvel[None, :], dvel[:-1]])
    dv_b = (
        dvel
        + 0.5 * np.cross(dtheta, dvel)
        + (np.cross(th_before, dvel) + np.cross(dv_before, dtheta)) / 12.0
    )
    c_all = _ref_dcm(np.vstack([s.q_nb[None, :], q]))
    c_prev, c = c_all[:-1], c_all[1:]
    dv_f_n = np.einsum("mij,mj->mi", c_prev, dv_b)
    g = earth.gravity_n(s.lat, s.h)
    cor = g - np.cross(2.0 * w_ie + w_en, s.vel_n)
    vel = s.vel_n + np.cumsum(dv_f_n + np.outer(dt, cor), axis=0)
    vel_prev = np.vstack([s.vel_n[None, :], vel[:-1]])
    dp_i = 0.5 * (vel_prev + vel) * dt[:, None]
    p = np.cumsum(dp_i, axis=0)
    dlat, dlon, dh = earth.enu_to_geodetic_increment(p, s.lat, s.h)
    lat, lon, h = s.lat + dlat, s.lon + dlon, s.h + dh
    T = float(t[-1] - s.t)
    c_mid = 0.5 * (c + c_prev)
    vel_mid = 0.5 * (vel_prev + vel)
    dv_f = dv_f_n.sum(axis=0)
    new = s.copy()
    new.t = float(t[-1])
    new.odoq = np.array([s.odoq[1], 0.0])
    new.q_nb = att.quat_normalize(q[-1])
    new.vel_n = vel[-1].copy()
    new.lat, new.lon, new.h = float(lat[-1]), float(lon[-1]), float(h[-1])
    res = BlockResult(
        t=t,
        q_nb=q,
        lat=lat,
        lon=lon,
        h=h,
        vel_n=vel,
        T=T,
        sum_c_dt=np.einsum("mij,m->ij", c_mid, dt),
        dv_f=dv_f,
        dp=p[-1].copy(),
        omega_b=dtheta.sum(axis=0) / T,
        f_mean_n=dv_f / T,
        mean_vel_b=np.einsum("mji,mj,m->i", c_mid, vel_mid, dt) / T,
        w_in=w_in,
        dp_dk=np.zeros(3),
        dp_dbore=np.zeros((3, 2)),
        path=float(np.abs(np.linalg.norm(dp_i, axis=1)).sum()),
        sum_c_w_dt=np.einsum("kai,kj->aij", c_mid, dtheta).reshape(3, 9),
        sum_c_f_dt=np.einsum("kai,kj->aij", c_prev, dvel).reshape(3, 9),
    )
    return new, res, Carry(dtheta[-1].copy(), dvel[-1].copy())


def _ref_dr_block(s, t, gyro, accel, ds, carry, lever_arm, earth_sign=1.0):
    w_ie = earth_sign * earth.earth_rate_n(s.lat)
    w_in = w_ie + earth.transport_rate_n(s.lat, s.h, s.vel_n)
    q, dtheta, dt = _ref_attitudes(s, t, gyro, carry, w_in)
    u, du = odometer_axis(s.bore)
    lever_x = dtheta[:, 1] * lever_arm[2] - dtheta[:, 2] * lever_arm[1]
    ds_c = (1.0 + s.k) * ds - lever_x
    c_all = _ref_dcm(np.vstack([s.q_nb[None, :], q]))
    c_prev, c = c_all[:-1], c_all[1:]
    c_mid = 0.5 * (c + c_prev)
    cu = c_mid @ u
    dp_i = cu * ds_c[:, None]
    p = np.cumsum(dp_i, axis=0)
    dlat, dlon, dh = earth.enu_to_geodetic_increment(p, s.lat, s.h)
    lat, lon, h = s.lat + dlat, s.lon + dlon, s.h + dh
    T = float(t[-1] - s.t)
    f_b = _ref_specific_force(s, accel)
    dv_f_n = np.einsum("mij,mj->mi", c_mid, f_b) * dt[:, None]
    new = s.copy()
    new.t = float(t[-1])
    new.q_nb = att.quat_normalize(q[-1])
    new.vel_n = p[-1] / T
    new.lat, new.lon, new.h = float(lat[-1]), float(lon[-1]), float(h[-1])
    res = BlockResult(
        t=t,
        q_nb=q,
        lat=lat,
        lon=lon,
        h=h,
        vel_n=dp_i / dt[:, None],
        T=T,
        sum_c_dt=np.einsum("mij,m->ij", c_mid, dt),
        dv_f=dv_f_n.sum(axis=0),
        dp=p[-1].copy(),
        omega_b=dtheta.sum(axis=0) / T,
        f_mean_n=dv_f_n.sum(axis=0) / T,
        mean_vel_b=u * (ds_c.sum() / T),
        w_in=w_in,
        dp_dk=(cu * ds[:, None]).sum(axis=0),
        dp_dbore=(1.0 + s.k) * np.einsum("mij,jk,m->ik", c_mid, du, ds),
        path=float(np.abs(ds_c).sum()),
        sum_c_w_dt=np.einsum("kai,kj->aij", c_mid, dtheta).reshape(3, 9),
        sum_c_f_dt=np.einsum("kai,kj->aij", c_mid, f_b * dt[:, None]).reshape(3, 9),
    )
    dvel = f_b * dt[:, None]
    return new, res, Carry(dtheta[-1].copy(), dvel[-1].copy())


# --- comparison ---

RTOL = 1e-12
STATE_FIELDS = ("vel_n", "q_nb", "bg", "ba", "k", "bore", "distance", "gm", "odoq", "am")
RESULT_FIELDS = (
    "t", "q_nb", "vel_n", "T", "sum_c_dt", "dv_f", "dp", "omega_b", "f_mean_n", "mean_vel_b",
    "w_in", "dp_dk", "dp_dbore", "path", "sum_c_w_dt", "sum_c_f_dt",
)  # fmt: skip


def _close(name: str, got, want, ulp_of: float = 0.0) -> None:
    """got == want to RTOL relative to the largest magnitude of want, plus 4 ulp of ulp_of."""
    got, want = np.asarray(got, dtype=float), np.asarray(want, dtype=float)
    assert got.shape == want.shape, name
    tol = RTOL * float(np.max(np.abs(want), initial=0.0)) + 4.0 * np.spacing(abs(ulp_of))
    np.testing.assert_allclose(got, want, rtol=0.0, atol=tol, err_msg=name)


def _compare(s0: NavState, got: tuple, want: tuple) -> None:
    (s1, r1, c1), (s2, r2, c2) = got, want
    assert s1.t == s2.t
    for f in STATE_FIELDS:
        _close("state." + f, getattr(s1, f), getattr(s2, f))
    for f in ("lat", "lon", "h"):  # increments from the block start, to see the last digits
        x0 = getattr(s0, f)
        _close("state." + f, getattr(s1, f) - x0, getattr(s2, f) - x0, ulp_of=x0)
        _close(f, getattr(r1, f) - x0, getattr(r2, f) - x0, ulp_of=x0)
    for f in RESULT_FIELDS:
        _close(f, getattr(r1, f), getattr(r2, f))
    assert isinstance(r1.T, float) and isinstance(r1.path, float)
    _close("carry.dtheta", c1.dtheta, c2.dtheta)
    _close("carry.dvel", c1.dvel, c2.dvel)


def _random_state(rng: np.random.Generator, errors: bool) -> NavState:
    q = rng.normal(size=4)
    return NavState(
        t=float(rng.uniform(-100.0, 100.0)),
        lat=float(rng.uniform(-1.2, 1.2)),
        lon=float(rng.uniform(-3.0, 3.0)),
        h=float(rng.uniform(-50.0, 500.0)),
        vel_n=rng.normal(size=3),
        q_nb=att.quat_normalize(q),
        bg=1e-3 * rng.normal(size=3),
        ba=0.05 * rng.normal(size=3),
        k=float(0.02 * rng.normal()),
        bore=0.03 * rng.normal(size=2),
        distance=float(rng.uniform(0.0, 1e4)),
        gm=0.01 * rng.normal(size=(3, 3)) if errors else None,
        odoq=0.01 * rng.normal(size=2),
        am=0.01 * rng.normal(size=(3, 3)) if errors else None,
    )


def _random_block(rng: np.random.Generator, s: NavState, m: int, rate_scale: float):
    t = s.t + np.cumsum(rng.uniform(0.002, 0.008, size=m))
    gyro = s.bg + rate_scale * rng.normal(size=(m, 3))
    accel = rng.normal(size=(m, 3)) + [0.0, 0.0, 9.8]
    ds = 0.005 + 0.002 * rng.normal(size=m)
    return t, gyro, accel, ds


CASES = [
    (m, errors, sign, rate)
    for m in (1, 2, 3, 20, 200)
    for errors, sign, rate in ((True, 1.0, 1.0), (False, -1.0, 0.3), (True, -1.0, 1e-7))
]


@pytest.mark.parametrize(("m", "errors", "earth_sign", "rate"), CASES)
def test_ins_block_matches_numpy_reference(m, errors, earth_sign, rate):
    rng = np.random.default_rng(1000 * m + int(errors) + 7 * int(earth_sign > 0))
    s = _random_state(rng, errors)
    carry = Carry(1e-3 * rng.normal(size=3), 1e-2 * rng.normal(size=3))
    t, gyro, accel, _ = _random_block(rng, s, m, rate)
    got = ins_block(s, t, gyro, accel, carry, earth_sign)
    want = _ref_ins_block(s, t, gyro, accel, carry, earth_sign)
    _compare(s, got, want)


@pytest.mark.parametrize(("m", "errors", "earth_sign", "rate"), CASES)
def test_dr_block_matches_numpy_reference(m, errors, earth_sign, rate):
    rng = np.random.default_rng(1000 * m + int(errors) + 7 * int(earth_sign > 0) + 3)
    s = _random_state(rng, errors)
    carry = Carry(1e-3 * rng.normal(size=3), 1e-2 * rng.normal(size=3))
    t, gyro, accel, ds = _random_block(rng, s, m, rate)
    lever = np.array([0.1, -0.2, 0.35])
    got = dr_block(s, t, gyro, accel, ds, carry, lever, earth_sign)
    want = _ref_dr_block(s, t, gyro, accel, ds, carry, lever, earth_sign)
    _compare(s, got, want)


@pytest.mark.parametrize("mode", ["ins", "dr"])
def test_chained_blocks_match_numpy_reference(mode):
    """Consecutive blocks of varying length, each started from the previous state and carry."""
    rng = np.random.default_rng(5)
    s_new = s_ref = _random_state(rng, errors=True)
    c_new = c_ref = Carry.zero()
    lever = np.array([0.0, 0.15, -0.1])
    for m in (1, 7, 2, 50, 200, 3):
        t, gyro, accel, ds = _random_block(rng, s_ref, m, 0.5)
        if mode == "ins":
            got = ins_block(s_new, t, gyro, accel, c_new)
            want = _ref_ins_block(s_ref, t, gyro, accel, c_ref)
        else:
            got = dr_block(s_new, t, gyro, accel, ds, c_new, lever)
            want = _ref_dr_block(s_ref, t, gyro, accel, ds, c_ref, lever)
        _compare(s_ref, got, want)
        s_new, _, c_new = got
        s_ref, _, c_ref = want


def test_inputs_of_any_layout_and_dtype():
    """Non-contiguous and float32 sample arrays give the results of contiguous float64 ones."""
    rng = np.random.default_rng(11)
    s = _random_state(rng, errors=True)
    t, gyro, accel, ds = _random_block(rng, s, 30, 0.5)
    lever = np.array([0.1, 0.0, 0.2])
    gyro_f = np.asfortranarray(gyro)
    accel_strided = np.repeat(accel, 2, axis=1)[:, ::2]
    assert not gyro_f.flags.c_contiguous and not accel_strided.flags.c_contiguous
    for f, args in (
        (ins_block, (s, t, gyro, accel, Carry.zero())),
        (dr_block, (s, t, gyro, accel, ds, Carry.zero(), lever)),
    ):
        want = f(*args)
        odd = list(args)
        odd[2], odd[3] = gyro_f, accel_strided
        _compare(s, f(*odd), want)
    accel32 = accel.astype(np.float32)
    _compare(
        s,
        ins_block(s, t, gyro, accel32, Carry.zero()),
        _ref_ins_block(s, t, gyro, accel32.astype(float), Carry.zero()),
    )


def test_kernels_compile_without_a_cache_directory(monkeypatch):
    """Where numba finds no writable cache directory it refuses cache=True; the kernels are
    then compiled without a cache instead of failing at import."""

    real_njit = jit.njit

    def njit_no_cache(**options):
        if options.get("cache"):
            raise RuntimeError("cannot cache function 'f': no locator available for file 'x.py'")
        return real_njit(**options)

    monkeypatch.setattr(jit, "njit", njit_no_cache)
    f = jit.kernel(lambda x: 2.0 * x)
    assert f(1.5) == 3.0
