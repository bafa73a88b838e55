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
- ``dir`` (2, optional): the direction of the straight section the pig is in (azimuth from
  north clockwise, pitch up; rad, ENU): a constant within each section, restarted at its
  start, that the pig's axis keeps to
  (:mod:`pipe_nav_core.model.measurements.section_direction`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.jit import kernel
from pipe_nav_core.records import Fields

Array = NDArray[np.float64]


class Layout:
    """Index slices of the error state for one mechanization mode ("ins" or "dr")."""

    def __init__(
        self,
        mode: str,
        gyro_errors: bool = False,
        accel_errors: bool = False,
        section_direction: bool = False,
    ) -> None:
        self.mode = mode
        names = ["att", "vel", "pos", "bg", "ba", "k", "bore", "odoq"]
        if mode != "ins":
            names.remove("vel")
            names.remove("odoq")
        if gyro_errors:
            names.append("gm")
        if accel_errors:
            names.append("am")
        if section_direction:
            names.append("dir")
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
            "dir": 2,
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
        self.dir = self.slices.get("dir")
        # the layout for the compiled kernels: block starts in L_* order (-1: absent), then n
        starts = [self.slices[b].start if b in self.slices else -1 for b in _BLOCKS]
        self.index = np.array([*starts, self.n], dtype=np.int64)

    @property
    def has_vel(self) -> bool:
        return self.vel is not None


# The nominal state as one flat float64 vector (NavState.vector / NavState.from_vector): the
# form the compiled kernels and the Recording use. Scalars (SV_*) and the starts of the blocks
# (I_*), in this order:
_sv = Fields()
SV_T, SV_LAT, SV_LON, SV_H = _sv(), _sv(), _sv(), _sv()  # s, rad, rad, m
I_VEL = _sv(3)  # m/s ENU
I_Q = _sv(4)  # [x, y, z, w] base_link -> ENU
I_BG = _sv(3)  # gyro bias rad/s base_link
I_BA = _sv(3)  # accelerometer bias m/s^2 base_link
SV_K = _sv()  # odometer scale error
I_BORE = _sv(2)  # boresight rad (yaw, pitch)
SV_DIST = _sv()  # chainage m
I_GM = _sv(9)  # gyro error matrix (row-major)
I_ODOQ = _sv(2)  # odometer reading errors m (start, end of the epoch)
I_AM = _sv(9)  # accelerometer error matrix (row-major)
I_DIR = _sv(2)  # the straight section's direction rad (azimuth, pitch; ENU)
SV_SIZE = _sv.size
SV_VEL, SV_Q = slice(I_VEL, I_VEL + 3), slice(I_Q, I_Q + 4)
SV_BG, SV_BA = slice(I_BG, I_BG + 3), slice(I_BA, I_BA + 3)
SV_BORE, SV_GM = slice(I_BORE, I_BORE + 2), slice(I_GM, I_GM + 9)
SV_ODOQ, SV_AM = slice(I_ODOQ, I_ODOQ + 2), slice(I_AM, I_AM + 9)
SV_DIR = slice(I_DIR, I_DIR + 2)

# The error-state layout as an int array for the kernels (Layout.index): the start of each
# block, -1 where the layout has none, and n last.
_BLOCKS = ("att", "vel", "pos", "bg", "ba", "k", "bore", "odoq", "gm", "am", "dir")
L_ATT, L_VEL, L_POS, L_BG, L_BA, L_K, L_BORE, L_ODOQ, L_GM, L_AM, L_DIR, L_N = range(
    len(_BLOCKS) + 1
)


@kernel
def odometer_axis(bore: Array) -> tuple[Array, Array]:
    """Unit odometer axis u in base_link for boresight (yaw, pitch) and du/d(yaw, pitch) (3, 2)."""
    yaw, pitch = bore[0], bore[1]
    norm = np.sqrt(1.0 + yaw * yaw + pitch * pitch)
    ux, uy, uz = 1.0 / norm, yaw / norm, pitch / norm
    # du = (d_raw - u (u^T d_raw)) / norm with d_raw = d[1, yaw, pitch] / d(yaw, pitch)
    du = np.empty((3, 2))
    du[0, 0], du[0, 1] = -ux * uy / norm, -ux * uz / norm
    du[1, 0], du[1, 1] = (1.0 - uy * uy) / norm, -uy * uz / norm
    du[2, 0], du[2, 1] = -uz * uy / norm, (1.0 - uz * uz) / norm
    return np.array([ux, uy, uz]), du


# the blocks whose error is a plain difference: (layout block, start in the flat state, size)
_ADDITIVE = (
    (L_VEL, I_VEL, 3),
    (L_BG, I_BG, 3),
    (L_BA, I_BA, 3),
    (L_K, SV_K, 1),
    (L_BORE, I_BORE, 2),
    (L_ODOQ, I_ODOQ, 2),
    (L_GM, I_GM, 9),
    (L_AM, I_AM, 9),
    (L_DIR, I_DIR, 2),
)


@kernel
def c_nb_k(sv: Array) -> Array:
    """C_nb (3, 3), base_link -> ENU, of the flat state sv."""
    c = np.empty((3, 3))
    att.dcm_into((sv[I_Q], sv[I_Q + 1], sv[I_Q + 2], sv[I_Q + 3]), c)
    return c


@kernel
def travel_axis_k(sv: Array) -> tuple[Array, Array]:
    """The direction of travel in ENU (unit; the odometer's axis u(boresight) of base_link:
    the pipe's axis, which a pig with its IMU mounted askew cones about as it rolls) and its
    derivative by the boresight (yaw, pitch) rad, (3, 2)."""
    c = c_nb_k(sv)
    u, du = odometer_axis(sv[I_BORE : I_BORE + 2])
    return c @ u, c @ du


@kernel
def inject_k(sv: Array, dx: Array, L: NDArray[np.int64]) -> Array:
    """Flat state sv (SV_SIZE,) corrected by the error state dx (n,) of layout L (Layout.index):
    truth = estimate (+) dx (NavState.inject)."""
    out = sv.copy()
    a, p = L[L_ATT], L[L_POS]
    dq = att.qrotvec(dx[a], dx[a + 1], dx[a + 2])
    q = att.qnormalize(att.qmul(dq, (sv[I_Q], sv[I_Q + 1], sv[I_Q + 2], sv[I_Q + 3])))
    for i in range(4):
        out[I_Q + i] = q[i]
    lat, h = sv[SV_LAT], sv[SV_H]
    rm, rn = earth._radii(lat)
    out[SV_LAT] = lat + dx[p + 1] / (rm + h)
    out[SV_LON] = sv[SV_LON] + dx[p] / ((rn + h) * np.cos(lat))
    out[SV_H] = h + dx[p + 2]
    for block, at, size in _ADDITIVE:
        j = L[block]
        if j >= 0:
            for i in range(size):
                out[at + i] += dx[j + i]
    return out


@kernel
def difference_k(sa: Array, sb: Array, L: NDArray[np.int64]) -> Array:
    """Error state dx (n,) with sa = sb (+) dx, flat states (first order in position)."""
    dx = np.zeros(L[L_N])
    qa = (sa[I_Q], sa[I_Q + 1], sa[I_Q + 2], sa[I_Q + 3])
    qb = (-sb[I_Q], -sb[I_Q + 1], -sb[I_Q + 2], sb[I_Q + 3])
    r = att.rotvec_of(att.qmul(qa, qb))
    a, p = L[L_ATT], L[L_POS]
    for i in range(3):
        dx[a + i] = r[i]
    rm, rn = earth._radii(sb[SV_LAT])
    dx[p] = (sa[SV_LON] - sb[SV_LON]) * (rn + sb[SV_H]) * np.cos(sb[SV_LAT])
    dx[p + 1] = (sa[SV_LAT] - sb[SV_LAT]) * (rm + sb[SV_H])
    dx[p + 2] = sa[SV_H] - sb[SV_H]
    for block, at, size in _ADDITIVE:
        j = L[block]
        if j >= 0:
            for i in range(size):
                dx[j + i] = sa[at + i] - sb[at + i]
    return dx


@dataclass
class NavState:
    """Nominal state at time t.

    lat, lon rad; h m (WGS84 ellipsoidal); vel_n (3,) m/s ENU; q_nb (4,) [x,y,z,w] base_link->ENU;
    bg (3,) rad/s and ba (3,) m/s^2 sensor biases in base_link; k odometer scale error;
    bore (2,) rad odometer boresight; distance m calibrated chainage; gm (3, 3) gyro
    scale-factor/misalignment matrix M (gyro = (I + M) omega + bg); odoq (2,) m odometer
    reading errors at the start and the end of the current epoch (INS mode); am (3, 3)
    accelerometer scale-factor/misalignment matrix N (accel = (I + N) f + ba); dir (2,) rad
    the straight section's direction (azimuth, pitch; ENU).
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
    dir: Array = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.bore is None:
            self.bore = np.zeros(2)
        if self.gm is None:
            self.gm = np.zeros((3, 3))
        if self.odoq is None:
            self.odoq = np.zeros(2)
        if self.am is None:
            self.am = np.zeros((3, 3))
        if self.dir is None:
            self.dir = np.zeros(2)

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
            dir=self.dir.copy(),
        )

    def vector(self) -> Array:
        """The state as one flat vector (SV_SIZE,) (index constants SV_* of this module)."""
        v = np.empty(SV_SIZE)
        v[SV_T], v[SV_LAT], v[SV_LON], v[SV_H] = self.t, self.lat, self.lon, self.h
        v[SV_VEL], v[SV_Q], v[SV_BG], v[SV_BA] = self.vel_n, self.q_nb, self.bg, self.ba
        v[SV_K], v[SV_BORE], v[SV_DIST] = self.k, self.bore, self.distance
        v[SV_GM], v[SV_ODOQ], v[SV_AM] = self.gm.reshape(9), self.odoq, self.am.reshape(9)
        v[SV_DIR] = self.dir
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
            dir=v[SV_DIR].copy(),
        )

    @property
    def c_nb(self) -> Array:
        q = self.q_nb
        c = np.empty((3, 3))
        att.dcm_into((float(q[0]), float(q[1]), float(q[2]), float(q[3])), c)
        return c

    def inject(self, dx: Array, layout: Layout) -> NavState:
        """The state corrected by the error-state vector dx (truth = estimate (+) dx)."""
        return NavState.from_vector(inject_k(self.vector(), np.asarray(dx, float), layout.index))

    def difference(self, other: NavState, layout: Layout) -> Array:
        """Error-state vector dx with self = other (+) dx (first order in position)."""
        return difference_k(self.vector(), other.vector(), layout.index)


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
    for src, dst in _additive_blocks(layout):
        out[:, dst] += d[:, src]
    return out


def difference_many(a: Array, b: Array, layout: Layout) -> Array:
    """Error-state vectors dx (K, n) with a = b (+) dx for flat states a, b (K, SV_SIZE):
    NavState.difference of every row at once (first order in position)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    dx = np.zeros((len(a), layout.n))
    dx[:, layout.att] = att.rotvec_from_quat(att.quat_mul(a[:, SV_Q], att.quat_conj(b[:, SV_Q])))
    rm, rn = earth.radii(b[:, SV_LAT])
    p = layout.pos.start
    dx[:, p] = (a[:, SV_LON] - b[:, SV_LON]) * (rn + b[:, SV_H]) * np.cos(b[:, SV_LAT])
    dx[:, p + 1] = (a[:, SV_LAT] - b[:, SV_LAT]) * (rm + b[:, SV_H])
    dx[:, p + 2] = a[:, SV_H] - b[:, SV_H]
    for src, dst in _additive_blocks(layout):
        dx[:, src] = a[:, dst] - b[:, dst]
    return dx


def _additive_blocks(layout: Layout) -> list[tuple[slice, slice]]:
    """(error-state slice, flat-state slice) of the blocks whose error is a plain difference."""
    pairs = [
        (layout.vel, SV_VEL),
        (layout.bg, SV_BG),
        (layout.ba, SV_BA),
        (layout.k, slice(SV_K, SV_K + 1)),
        (layout.bore, SV_BORE),
        (layout.gm, SV_GM),
        (layout.odoq, SV_ODOQ),
        (layout.am, SV_AM),
        (layout.dir, SV_DIR),
    ]
    return [(src, dst) for src, dst in pairs if src is not None]


# A gyro whose angle random walk (rad/sqrt(s)) is below this share of straight_pipe_wander
# over a metre at 1 m/s holds a straight section's direction better than the section
# direction state could (BENCHMARKS.md, "The section direction": the tactical 10 km line's
# error the same to 0.1 mm, for 13 % of its time; industrial 0.4 %; consumer 11-17 %)
DIRECTION_ARW_SHARE = 0.1


def layout_for(config: NavConfig) -> Layout:
    """The error-state layout of a NavConfig (mode, gyro_error_states, accel_error_states, and
    the section direction where straight_pipe_wander is set and the gyro's angle random walk
    is at least DIRECTION_ARW_SHARE of it per sqrt(s) at 1 m/s)."""
    wander = config.straight_pipe_wander
    return Layout(
        config.mode,
        config.gyro_error_states,
        config.accel_error_states,
        wander > 0 and config.imu_spec().gyro_arw >= DIRECTION_ARW_SHARE * wander,
    )
