"""Rotations: quaternions (scalar-last [x, y, z, w]), rotation vectors, direction cosine matrices.

``q_nb`` / ``C_nb`` rotate base_link (FLU) vectors into ENU. All functions are vectorized over
leading axes (a single quaternion or vector takes a scalar ``math`` path: the filter calls them
once per epoch). Angles are radians. People-facing attitude (roll, pitch positive nose up, azimuth
clockwise from true north) is produced by :func:`euler_from_dcm`; the CLI converts to degrees.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.jit import kernel

Array = NDArray[np.float64]
Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]  # [x, y, z, w]


def skew(v: ArrayLike) -> Array:
    """Cross-product matrix [v x], shape (..., 3, 3)."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros_like(v[..., 0])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], axis=-1),
            np.stack([v[..., 2], z, -v[..., 0]], axis=-1),
            np.stack([-v[..., 1], v[..., 0], z], axis=-1),
        ],
        axis=-2,
    )


def quat_mul(p: ArrayLike, q: ArrayLike) -> Array:
    """Hamilton product p * q of scalar-last quaternions (rotation q first, then p)."""
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    if p.ndim == 1 and q.ndim == 1:
        px, py, pz, pw = p.tolist()
        qx, qy, qz, qw = q.tolist()
        return np.array(
            [
                pw * qx + px * qw + py * qz - pz * qy,
                pw * qy - px * qz + py * qw + pz * qx,
                pw * qz + px * qy - py * qx + pz * qw,
                pw * qw - px * qx - py * qy - pz * qz,
            ]
        )
    px, py, pz, pw = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
            pw * qw - px * qx - py * qy - pz * qz,
        ],
        axis=-1,
    )


def quat_conj(q: ArrayLike) -> Array:
    """Conjugate (inverse of a unit quaternion)."""
    q = np.array(q, dtype=np.float64)
    q[..., :3] *= -1.0
    return q


def quat_normalize(q: ArrayLike) -> Array:
    """Unit quaternion with non-negative scalar part."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim == 1:
        x, y, z, w = q.tolist()
        norm = math.sqrt(x * x + y * y + z * z + w * w)
        if w < 0.0:
            norm = -norm
        return np.array([x / norm, y / norm, z / norm, w / norm])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def quat_from_rotvec(rv: ArrayLike) -> Array:
    """Quaternion of the rotation vector rv (rad), exact, with a series near zero."""
    rv = np.asarray(rv, dtype=np.float64)
    if rv.ndim == 1:
        x, y, z = rv.tolist()
        th2 = x * x + y * y + z * z
        th = math.sqrt(th2)
        if th < 1e-6:
            k, w = 0.5 - th2 / 48.0, 1.0 - th2 / 8.0
        else:
            k, w = math.sin(0.5 * th) / th, math.cos(0.5 * th)
        return np.array([x * k, y * k, z * k, w])
    th2 = np.sum(rv * rv, axis=-1, keepdims=True)
    th = np.sqrt(th2)
    small = th < 1e-6
    safe = np.where(small, 1.0, th)
    k = np.where(small, 0.5 - th2 / 48.0, np.sin(0.5 * safe) / safe)
    w = np.where(small, 1.0 - th2 / 8.0, np.cos(0.5 * safe))
    return np.concatenate([rv * k, w], axis=-1)


def rotvec_from_quat(q: ArrayLike) -> Array:
    """Rotation vector (rad) of a unit quaternion, angle in [0, pi]."""
    q = quat_normalize(q)
    if q.ndim == 1:
        x, y, z, w = q.tolist()
        s = math.sqrt(x * x + y * y + z * z)
        k = 2.0 if s < 1e-9 else 2.0 * math.atan2(s, w) / s
        return np.array([x * k, y * k, z * k])
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(s, q[..., 3:4])
    small = s < 1e-9
    k = np.where(small, 2.0, ang / np.where(small, 1.0, s))
    return q[..., :3] * k


def dcm_from_quat(q: ArrayLike) -> Array:
    """Rotation matrix of a unit quaternion, shape (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return np.stack(
        [
            np.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)], axis=-1),
            np.stack([2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)], axis=-1),
            np.stack([2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], axis=-1),
        ],
        axis=-2,
    )


def body_x_axis(q: ArrayLike) -> Array:
    """The body x axis (base_link's, along the pipe) in the navigation frame (ENU) of unit
    quaternions q (..., 4): the first column of :func:`dcm_from_quat`, the same arithmetic,
    without the other two (shape (..., 3))."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], axis=-1)


def quat_from_dcm(c: ArrayLike) -> Array:
    """Unit quaternion of a rotation matrix, shape (..., 4) (robust for any angle: each
    matrix's quaternion from its largest of trace and diagonal, as scipy's
    Rotation.from_matrix, bit for bit (tested), without its 0.2 s import)."""
    c = np.asarray(c, dtype=np.float64)
    m = c.reshape(-1, 3, 3)
    d = np.diagonal(m, axis1=-2, axis2=-1)
    tr = d.sum(axis=-1)
    choice = np.argmax(np.concatenate([d, tr[:, None]], axis=-1), axis=-1)
    q = np.empty((len(m), 4))
    rows = np.arange(len(m))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        s = rows[choice == i]
        ms = m[s]
        q[s, i] = 1 - tr[s] + 2 * ms[:, i, i]
        q[s, j] = ms[:, j, i] + ms[:, i, j]
        q[s, k] = ms[:, k, i] + ms[:, i, k]
        q[s, 3] = ms[:, k, j] - ms[:, j, k]
    s = rows[choice == 3]
    ms = m[s]
    q[s, 0] = ms[:, 2, 1] - ms[:, 1, 2]
    q[s, 1] = ms[:, 0, 2] - ms[:, 2, 0]
    q[s, 2] = ms[:, 1, 0] - ms[:, 0, 1]
    q[s, 3] = 1 + tr[s]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return quat_normalize(q.reshape(c.shape[:-2] + (4,)))


def dcm_from_rotvec(rv: ArrayLike) -> Array:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    return dcm_from_quat(quat_from_rotvec(rv))


def quat_cumprod(q0: ArrayLike, dq: ArrayLike) -> Array:
    """Attitudes q0 * dq[0] * dq[1] * ... * dq[i] for every i, shape (N, 4).

    Body-frame increments dq (N, 4) are chained on the right. A log-depth parallel prefix scan
    keeps the work vectorized.
    """
    acc = np.array(dq, dtype=np.float64)
    n = acc.shape[0]
    step = 1
    while step < n:
        acc[step:] = quat_mul(acc[:-step].copy(), acc[step:])
        step *= 2
    return quat_mul(np.asarray(q0, dtype=np.float64), acc)


def coning_increments(dtheta: ArrayLike, prev: ArrayLike | None = None) -> Array:
    """Attitude increments with the two-sample coning correction.

    dtheta: (N, 3) angle increments (rad), each the mean rate times the sample interval.
    prev: the increment preceding dtheta[0] (zeros if None). Returns (N, 3) rotation vectors
    dtheta[i] + (1/12) dtheta[i-1] x dtheta[i].
    """
    d = np.asarray(dtheta, dtype=np.float64)
    p = np.zeros(3) if prev is None else np.asarray(prev, dtype=np.float64)
    before = np.vstack([p[None, :], d[:-1]])
    return d + np.cross(before, d) / 12.0


def euler_from_dcm(c_nb: ArrayLike) -> tuple[Array, Array, Array]:
    """(roll, pitch, azimuth) in rad from C_nb (base_link FLU -> ENU).

    pitch: positive nose up, in [-pi/2, pi/2]; roll: about the body x axis, right side down
    positive, in (-pi, pi]; azimuth: clockwise from true north, in [0, 2 pi).
    """
    c = np.asarray(c_nb, dtype=np.float64)
    pitch = np.arcsin(np.clip(c[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(c[..., 2, 1], c[..., 2, 2])
    azimuth = np.mod(np.arctan2(c[..., 0, 0], c[..., 1, 0]), 2.0 * np.pi)
    return roll, pitch, azimuth


def turn_deg(angle: ArrayLike, decimals: int) -> Array:
    """Angles (rad) in degrees in [0, 360) as written with ``decimals`` decimals (azimuths,
    curvature planes): rounded first, then wrapped, so that one a hair under a full turn is
    written 0, not 360 (outside the range the files document)."""
    d = np.round(np.mod(np.degrees(angle), 360.0), decimals)
    return np.where(d >= 360.0, 0.0, d)


def dcm_from_euler(roll: ArrayLike, pitch: ArrayLike, azimuth: ArrayLike) -> Array:
    """C_nb (FLU -> ENU) from roll, pitch (nose up) and azimuth (clockwise from north), rad.

    C_nb = Rz(pi/2 - azimuth) * Ry(-pitch) * Rx(roll).
    """
    roll, pitch, azimuth = np.broadcast_arrays(
        np.asarray(roll, float), np.asarray(pitch, float), np.asarray(azimuth, float)
    )
    yaw = 0.5 * np.pi - azimuth
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    # Ry(-pitch): rotation about y by -pitch, so that +pitch lifts the nose (x towards +z).
    return np.stack(
        [
            np.stack([cy * cp, -sy * cr - cy * sp * sr, sy * sr - cy * sp * cr], axis=-1),
            np.stack([sy * cp, cy * cr - sy * sp * sr, -cy * sr - sy * sp * cr], axis=-1),
            np.stack([sp, cp * sr, cp * cr], axis=-1),
        ],
        axis=-2,
    )


def quat_from_euler(roll: ArrayLike, pitch: ArrayLike, azimuth: ArrayLike) -> Array:
    """q_nb from roll, pitch (nose up) and azimuth (clockwise from north), rad."""
    return quat_from_dcm(dcm_from_euler(roll, pitch, azimuth))


# --- compiled scalar helpers for the numba kernels (3-vectors and quaternions as tuples) ---


@kernel
def cross3(a: Vec3 | Array, b: Vec3 | Array) -> Vec3:
    """a x b of two 3-vectors (tuples or arrays)."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@kernel
def skew_k(v: Vec3 | Array) -> Array:
    """Cross-product matrix [v x] (3, 3) of one 3-vector (as skew)."""
    out = np.zeros((3, 3))
    out[0, 1], out[0, 2], out[1, 2] = -v[2], v[1], -v[0]
    out[1, 0], out[2, 0], out[2, 1] = v[2], -v[1], v[0]
    return out


@kernel
def qmul(p: Quat, q: Quat) -> Quat:
    """Hamilton product p * q of scalar-last quaternions (as attitude.quat_mul)."""
    px, py, pz, pw = p
    qx, qy, qz, qw = q
    return (
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
        pw * qw - px * qx - py * qy - pz * qz,
    )


@kernel
def qrotvec(x: float, y: float, z: float) -> Quat:
    """Quaternion of the rotation vector (x, y, z), rad (as attitude.quat_from_rotvec)."""
    th2 = x * x + y * y + z * z
    th = np.sqrt(th2)
    if th < 1e-6:
        k = 0.5 - th2 / 48.0
        w = 1.0 - th2 / 8.0
    else:
        k = np.sin(0.5 * th) / th
        w = np.cos(0.5 * th)
    return (x * k, y * k, z * k, w)


@kernel
def dcm_into(q: Quat, c: Array) -> None:
    """Write the rotation matrix of the unit quaternion q [x, y, z, w] into c (3, 3)."""
    x, y, z, w = q
    c[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    c[0, 1] = 2.0 * (x * y - w * z)
    c[0, 2] = 2.0 * (x * z + w * y)
    c[1, 0] = 2.0 * (x * y + w * z)
    c[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    c[1, 2] = 2.0 * (y * z - w * x)
    c[2, 0] = 2.0 * (x * z - w * y)
    c[2, 1] = 2.0 * (y * z + w * x)
    c[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@kernel
def inv3(a: Array) -> Array:
    """Inverse of a 3x3 matrix (adjugate over determinant)."""
    inv = np.empty((3, 3))
    inv[0, 0] = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    inv[1, 0] = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    inv[2, 0] = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    inv[0, 1] = a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]
    inv[1, 1] = a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]
    inv[2, 1] = a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]
    inv[0, 2] = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
    inv[1, 2] = a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]
    inv[2, 2] = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    det = a[0, 0] * inv[0, 0] + a[0, 1] * inv[1, 0] + a[0, 2] * inv[2, 0]
    return inv / det


@kernel
def qnormalize(q: Quat) -> Quat:
    """Unit quaternion with non-negative scalar part (as quat_normalize)."""
    x, y, z, w = q
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    if w < 0.0:
        norm = -norm
    return (x / norm, y / norm, z / norm, w / norm)


@kernel
def rotvec_of(q: Quat) -> Vec3:
    """Rotation vector (rad) of a quaternion, angle in [0, pi] (as rotvec_from_quat)."""
    x, y, z, w = qnormalize(q)
    s = np.sqrt(x * x + y * y + z * z)
    k = 2.0 if s < 1e-9 else 2.0 * np.arctan2(s, w) / s
    return (x * k, y * k, z * k)


@kernel(nogil=True)
def slerp_rows(q: Array, i: NDArray[np.int64], f: Array, out: Array) -> None:
    """out[j] (M, 4) <- the slerp from q0 = q[i[j]] to q1 = q[i[j] + 1] at fraction f[j] (q (N,
    4) unit quaternions; the shorter way round): q0 times the quaternion of f[j] times the
    rotation vector of q0^-1 q1, normalized (quat_mul, rotvec_from_quat, quat_from_rotvec and
    quat_normalize's formulas, sample by sample, without their temporaries)."""
    for j in range(i.shape[0]):
        a, b = i[j], i[j] + 1
        q0 = (q[a, 0], q[a, 1], q[a, 2], q[a, 3])
        q1 = (q[b, 0], q[b, 1], q[b, 2], q[b, 3])
        rx, ry, rz = rotvec_of(qmul((-q0[0], -q0[1], -q0[2], q0[3]), q1))
        r = qnormalize(qmul(q0, qrotvec(rx * f[j], ry * f[j], rz * f[j])))
        out[j, 0], out[j, 1], out[j, 2], out[j, 3] = r
