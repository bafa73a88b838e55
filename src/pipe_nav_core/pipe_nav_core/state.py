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

from dataclasses import dataclass, replace

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


def skew3(v: Array) -> Array:
    """Cross-product matrix [v x] of one 3-vector (as attitude.skew, for the per-epoch
    Jacobians, where numpy's stacking overhead dominated)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def dcm1(q: Array) -> Array:
    """C_nb of one unit quaternion [x, y, z, w] (as attitude.dcm_from_quat, scalar path)."""
    x, y, z, w = (float(a) for a in q)
    return np.array(
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
        ]
    )


def odometer_axis(bore: Array) -> tuple[Array, Array]:
    """Unit odometer axis u in base_link for boresight (yaw, pitch) and du/d(yaw, pitch) (3, 2)."""
    raw = np.array([1.0, bore[0], bore[1]])
    norm = np.linalg.norm(raw)
    u = raw / norm
    d_raw = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    du = (d_raw - np.outer(u, u @ d_raw)) / norm
    return u, du


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
        return replace(
            self,
            vel_n=self.vel_n.copy(),
            q_nb=self.q_nb.copy(),
            bg=self.bg.copy(),
            ba=self.ba.copy(),
            bore=self.bore.copy(),
            gm=self.gm.copy(),
            odoq=self.odoq.copy(),
            am=self.am.copy(),
        )

    @property
    def c_nb(self) -> Array:
        return dcm1(self.q_nb)

    def inject(self, dx: Array, layout: Layout) -> NavState:
        """The state corrected by the error-state vector dx (truth = estimate (+) dx)."""
        s = self.copy()
        phi = dx[layout.att]
        s.q_nb = att.quat_normalize(att.quat_mul(att.quat_from_rotvec(phi), s.q_nb))
        if layout.vel is not None:
            s.vel_n = s.vel_n + dx[layout.vel]
        dlat, dlon, dh = earth.enu_to_geodetic_increment(dx[layout.pos], s.lat, s.h)
        s.lat, s.lon, s.h = float(s.lat + dlat), float(s.lon + dlon), float(s.h + dh)
        s.bg = s.bg + dx[layout.bg]
        s.ba = s.ba + dx[layout.ba]
        s.k = float(s.k + dx[layout.k][0])
        s.bore = s.bore + dx[layout.bore]
        if layout.odoq is not None:
            s.odoq = s.odoq + dx[layout.odoq]
        if layout.gm is not None:
            s.gm = s.gm + dx[layout.gm].reshape(3, 3)
        if layout.am is not None:
            s.am = s.am + dx[layout.am].reshape(3, 3)
        return s

    def difference(self, other: NavState, layout: Layout) -> Array:
        """Error-state vector dx with self = other (+) dx (first order in position)."""
        dx = np.zeros(layout.n)
        dq = att.quat_mul(self.q_nb, att.quat_conj(other.q_nb))
        dx[layout.att] = att.rotvec_from_quat(dq)
        if layout.vel is not None:
            dx[layout.vel] = self.vel_n - other.vel_n
        rm, rn = earth.radii(other.lat)
        dx[layout.pos] = [
            (self.lon - other.lon) * (rn + other.h) * np.cos(other.lat),
            (self.lat - other.lat) * (rm + other.h),
            self.h - other.h,
        ]
        dx[layout.bg] = self.bg - other.bg
        dx[layout.ba] = self.ba - other.ba
        dx[layout.k] = self.k - other.k
        dx[layout.bore] = self.bore - other.bore
        if layout.odoq is not None:
            dx[layout.odoq] = self.odoq - other.odoq
        if layout.gm is not None:
            dx[layout.gm] = (self.gm - other.gm).reshape(9)
        if layout.am is not None:
            dx[layout.am] = (self.am - other.am).reshape(9)
        return dx


def layout_for(config: NavConfig) -> Layout:
    """The error-state layout of a NavConfig (mode, gyro_error_states, accel_error_states)."""
    return Layout(config.mode, config.gyro_error_states, config.accel_error_states)
