"""Nominal navigation state and the error-state layout shared by the filter, the smoothers and
every measurement model.

Error state (truth minus estimate), navigation frame ENU:
- ``att`` (3): attitude error phi, rad: C_nb(true) = (I + [phi x]) C_nb(estimate);
- ``vel`` (3): velocity error, m/s (INS mode only);
- ``pos`` (3): position error, m, east/north/up;
- ``bg`` (3): gyro bias error, rad/s (body); ``ba`` (3): accelerometer bias error, m/s^2 (body);
- ``k`` (1): odometer scale-factor error: true distance = (1 + k) * measured;
- ``bore`` (2): odometer boresight (yaw, pitch), rad: the odometer axis in base_link is
  u = normalize([1, yaw, pitch]);
- ``odoq`` (2, INS mode): odometer reading errors (m), [at the start, at the end] of the
  current epoch: the quantization of the wheel count. They enter the distance increment of one
  epoch as their difference and never accumulate; each epoch the end value becomes the start
  value and a fresh end value is drawn (variance resolution^2 / 12);
- ``gm`` (9, optional): gyro scale-factor and misalignment matrix M, row-major, where the gyro
  measures (I + M) omega + bias (matters when the pig rolls through whole turns);
- ``am`` (9, optional): accelerometer scale-factor and misalignment matrix N, row-major, where
  the accelerometer measures (I + N) f + bias (with a consumer MEMS a 1 % scale factor turns
  gravity into tens of mg of apparent bias whenever the pig rolls).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import attitude as att
from . import earth
from .config import NavConfig

Array = NDArray[np.float64]


class Layout:
    """Index slices of the error state for one mechanization mode ("ins" or "dr")."""

    def __init__(self, mode: str, gyro_errors: bool = False, accel_errors: bool = False) -> None:
        self.mode = mode
        names = ["att", "vel", "pos", "bg", "ba", "k", "bore", "odoq"]
        if mode != "ins":
            names.remove("vel")
            names.remove("odoq")
        if gyro_errors:
            names.append("gm")
        if accel_errors:
            names.append("am")
        sizes = {
            "att": 3,
            "vel": 3,
            "pos": 3,
            "bg": 3,
            "ba": 3,
            "k": 1,
            "bore": 2,
            "odoq": 2,
            "gm": 9,
            "am": 9,
        }
        start = 0
        self.slices: dict[str, slice] = {}
        for name in names:
            self.slices[name] = slice(start, start + sizes[name])
            start += sizes[name]
        self.n = start
        self.att = self.slices["att"]
        self.vel = self.slices.get("vel")
        self.pos = self.slices["pos"]
        self.bg = self.slices["bg"]
        self.ba = self.slices["ba"]
        self.k = self.slices["k"]
        self.bore = self.slices["bore"]
        self.odoq = self.slices.get("odoq")
        self.gm = self.slices.get("gm")
        self.am = self.slices.get("am")

    @property
    def has_vel(self) -> bool:
        return self.vel is not None


# The nominal state as one flat float64 vector (NavState.vector / NavState.from_vector): the
# form the compiled kernels and the Recording use. Indices:
SV_T, SV_LAT, SV_LON, SV_H = 0, 1, 2, 3  # s, rad, rad, m
SV_VEL = slice(4, 7)  # m/s ENU
SV_Q = slice(7, 11)  # [x, y, z, w] base_link -> ENU
SV_BG = slice(11, 14)  # rad/s base_link
SV_BA = slice(14, 17)  # m/s^2 base_link
SV_K = 17  # odometer scale error
SV_BORE = slice(18, 20)  # rad (yaw, pitch)
SV_DIST = 20  # m calibrated chainage
SV_GM = slice(21, 30)  # gyro error matrix M, row-major
SV_ODOQ = slice(30, 32)  # m odometer reading errors (start, end of the epoch)
SV_AM = slice(32, 41)  # accelerometer error matrix N, row-major
SV_SIZE = 41


def skew3(v: Array) -> Array:
    """Cross-product matrix [v x] of one 3-vector (as attitude.skew, for the per-epoch
    Jacobians, where numpy's stacking overhead dominated)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def dcm1(q: Array) -> Array:
    """C_nb of one unit quaternion [x, y, z, w] (as attitude.dcm_from_quat, scalar path)."""
    x, y, z, w = np.asarray(q, dtype=np.float64).tolist()
    return np.array(
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
        ]
    )


def odometer_axis(bore: Array) -> tuple[Array, Array]:
    """Unit odometer axis u in base_link for boresight (yaw, pitch) and du/d(yaw, pitch) (3, 2)."""
    yaw, pitch = float(bore[0]), float(bore[1])
    norm = math.sqrt(1.0 + yaw * yaw + pitch * pitch)
    ux, uy, uz = 1.0 / norm, yaw / norm, pitch / norm
    # du = (d_raw - u (u^T d_raw)) / norm with d_raw = d[1, yaw, pitch] / d(yaw, pitch)
    du = np.array([[-ux * uy, -ux * uz], [1.0 - uy * uy, -uy * uz], [-uz * uy, 1.0 - uz * uz]])
    return np.array([ux, uy, uz]), du / norm


@dataclass
class NavState:
    """Nominal state at time t.

    lat, lon rad; h m (WGS84 ellipsoidal); vel_n (3,) m/s ENU; q_nb (4,) [x,y,z,w] base_link->ENU;
    bg (3,) rad/s and ba (3,) m/s^2 sensor biases in base_link; k odometer scale error;
    bore (2,) rad odometer boresight; distance m calibrated chainage; gm (3, 3) gyro
    scale-factor/misalignment matrix M (gyro = (I + M) omega + bg); odoq (2,) m odometer
    reading errors at the start and the end of the current epoch (INS mode); am (3, 3)
    accelerometer scale-factor/misalignment matrix N (accel = (I + N) f + ba).
    """

    t: float
    lat: float
    lon: float
    h: float
    vel_n: Array
    q_nb: Array
    bg: Array
    ba: Array
    k: float = 0.0
    bore: Array = None  # type: ignore[assignment]
    distance: float = 0.0
    gm: Array = None  # type: ignore[assignment]
    odoq: Array = None  # type: ignore[assignment]
    am: Array = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.bore is None:
            self.bore = np.zeros(2)
        if self.gm is None:
            self.gm = np.zeros((3, 3))
        if self.odoq is None:
            self.odoq = np.zeros(2)
        if self.am is None:
            self.am = np.zeros((3, 3))

    def copy(self) -> NavState:
        return NavState(
            t=self.t,
            lat=self.lat,
            lon=self.lon,
            h=self.h,
            vel_n=self.vel_n.copy(),
            q_nb=self.q_nb.copy(),
            bg=self.bg.copy(),
            ba=self.ba.copy(),
            k=self.k,
            bore=self.bore.copy(),
            distance=self.distance,
            gm=self.gm.copy(),
            odoq=self.odoq.copy(),
            am=self.am.copy(),
        )

    def vector(self) -> Array:
        """The state as one flat vector (SV_SIZE,) (index constants SV_* of this module)."""
        v = np.empty(SV_SIZE)
        v[SV_T], v[SV_LAT], v[SV_LON], v[SV_H] = self.t, self.lat, self.lon, self.h
        v[SV_VEL], v[SV_Q], v[SV_BG], v[SV_BA] = self.vel_n, self.q_nb, self.bg, self.ba
        v[SV_K], v[SV_BORE], v[SV_DIST] = self.k, self.bore, self.distance
        v[SV_GM], v[SV_ODOQ], v[SV_AM] = self.gm.reshape(9), self.odoq, self.am.reshape(9)
        return v

    @classmethod
    def from_vector(cls, v: Array) -> NavState:
        """The state of a flat vector made by :meth:`vector` (copies)."""
        v = np.asarray(v, dtype=np.float64)
        return cls(
            t=float(v[SV_T]),
            lat=float(v[SV_LAT]),
            lon=float(v[SV_LON]),
            h=float(v[SV_H]),
            vel_n=v[SV_VEL].copy(),
            q_nb=v[SV_Q].copy(),
            bg=v[SV_BG].copy(),
            ba=v[SV_BA].copy(),
            k=float(v[SV_K]),
            bore=v[SV_BORE].copy(),
            distance=float(v[SV_DIST]),
            gm=v[SV_GM].reshape(3, 3).copy(),
            odoq=v[SV_ODOQ].copy(),
            am=v[SV_AM].reshape(3, 3).copy(),
        )

    @property
    def c_nb(self) -> Array:
        return dcm1(self.q_nb)

    def inject(self, dx: Array, layout: Layout) -> NavState:
        """The state corrected by the error-state vector dx (truth = estimate (+) dx)."""
        q_nb = att.quat_normalize(att.quat_mul(att.quat_from_rotvec(dx[layout.att]), self.q_nb))
        dlat, dlon, dh = earth.enu_to_geodetic_increment(dx[layout.pos], self.lat, self.h)
        gm, am = self.gm, self.am
        return NavState(
            t=self.t,
            lat=float(self.lat + dlat),
            lon=float(self.lon + dlon),
            h=float(self.h + dh),
            vel_n=self.vel_n + dx[layout.vel] if layout.vel is not None else self.vel_n.copy(),
            q_nb=q_nb,
            bg=self.bg + dx[layout.bg],
            ba=self.ba + dx[layout.ba],
            k=self.k + float(dx[layout.k.start]),
            bore=self.bore + dx[layout.bore],
            distance=self.distance,
            gm=gm + dx[layout.gm].reshape(3, 3) if layout.gm is not None else gm.copy(),
            odoq=self.odoq + dx[layout.odoq] if layout.odoq is not None else self.odoq.copy(),
            am=am + dx[layout.am].reshape(3, 3) if layout.am is not None else am.copy(),
        )

    def difference(self, other: NavState, layout: Layout) -> Array:
        """Error-state vector dx with self = other (+) dx (first order in position)."""
        dx = np.zeros(layout.n)
        dq = att.quat_mul(self.q_nb, att.quat_conj(other.q_nb))
        dx[layout.att] = att.rotvec_from_quat(dq)
        if layout.vel is not None:
            dx[layout.vel] = self.vel_n - other.vel_n
        rm, rn = earth.radii(float(other.lat))
        p = layout.pos.start
        dx[p] = (self.lon - other.lon) * (rn + other.h) * math.cos(other.lat)
        dx[p + 1] = (self.lat - other.lat) * (rm + other.h)
        dx[p + 2] = self.h - other.h
        dx[layout.bg] = self.bg - other.bg
        dx[layout.ba] = self.ba - other.ba
        dx[layout.k.start] = self.k - other.k
        dx[layout.bore] = self.bore - other.bore
        if layout.odoq is not None:
            dx[layout.odoq] = self.odoq - other.odoq
        if layout.gm is not None:
            dx[layout.gm] = (self.gm - other.gm).reshape(9)
        if layout.am is not None:
            dx[layout.am] = (self.am - other.am).reshape(9)
        return dx


def inject_many(states: Array, dx: Array, layout: Layout) -> Array:
    """Flat states (K, SV_SIZE) corrected by error-state vectors dx (K, n): NavState.inject of
    every row at once (t and distance unchanged)."""
    out = np.array(states, dtype=np.float64)
    d = np.asarray(dx, dtype=np.float64)
    q = att.quat_mul(att.quat_from_rotvec(d[:, layout.att]), out[:, SV_Q])
    out[:, SV_Q] = att.quat_normalize(q)
    dlat, dlon, dh = earth.enu_to_geodetic_increment(d[:, layout.pos], out[:, SV_LAT], out[:, SV_H])
    out[:, SV_LAT] += dlat
    out[:, SV_LON] += dlon
    out[:, SV_H] += dh
    pairs = [
        (layout.vel, SV_VEL),
        (layout.bg, SV_BG),
        (layout.ba, SV_BA),
        (layout.k, slice(SV_K, SV_K + 1)),
    ]
    pairs += [
        (layout.bore, SV_BORE),
        (layout.gm, SV_GM),
        (layout.odoq, SV_ODOQ),
        (layout.am, SV_AM),
    ]
    for src, dst in pairs:
        if src is not None:
            out[:, dst] += d[:, src]
    return out


def layout_for(config: NavConfig) -> Layout:
    """The error-state layout of a NavConfig (mode, gyro_error_states, accel_error_states)."""
    return Layout(config.mode, config.gyro_error_states, config.accel_error_states)
