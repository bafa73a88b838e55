"""Sensor samples, markers and results: the data that flows between the modules.

Conventions (see INTERFACES.md):
- time: seconds on the bag's header-stamp clock (float64);
- IMU and magnetometer vectors are in ``imu_link`` until :func:`SensorLog.to_base_link` rotates
  them into ``base_link`` (x forward, y left, z up);
- navigation frame ``n`` is local East-North-Up; positions are geodetic WGS84 with latitude and
  longitude in radians and ellipsoidal height in metres;
- quaternions are scalar-last ``[x, y, z, w]`` (ROS and scipy order) and rotate ``base_link``
  vectors into ENU (``q_nb``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def _as2d(a: object, cols: int) -> FloatArray:
    arr = np.asarray(a, dtype=np.float64)
    return arr.reshape(-1, cols)


@dataclass
class ImuSamples:
    """IMU samples.

    t: (N,) s, sample stamps, strictly increasing.
    gyro: (N, 3) rad/s, MEAN angular rate over (t[i-1], t[i]] in the sensor frame.
    accel: (N, 3) m/s^2, MEAN specific force over the same interval (about +9.8 on z at rest).
    """

    t: FloatArray
    gyro: FloatArray
    accel: FloatArray

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        self.gyro = _as2d(self.gyro, 3)
        self.accel = _as2d(self.accel, 3)

    def __len__(self) -> int:
        return len(self.t)

    def slice(self, s: slice | NDArray[np.bool_] | NDArray[np.int64]) -> ImuSamples:
        return ImuSamples(self.t[s], self.gyro[s], self.accel[s])


@dataclass
class OdometerSamples:
    """Wheel odometer samples.

    t: (N,) s; distance: (N,) m, cumulative distance along the pipe since the start of the log
    (raw, before scale calibration); speed: (N,) m/s forward speed as reported by the odometer.
    """

    t: FloatArray
    distance: FloatArray
    speed: FloatArray

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        self.distance = np.asarray(self.distance, dtype=np.float64).reshape(-1)
        self.speed = np.asarray(self.speed, dtype=np.float64).reshape(-1)

    def __len__(self) -> int:
        return len(self.t)

    def slice(self, s: slice | NDArray[np.bool_] | NDArray[np.int64]) -> OdometerSamples:
        return OdometerSamples(self.t[s], self.distance[s], self.speed[s])


@dataclass
class MagSamples:
    """Magnetometer samples. t: (N,) s; field: (N, 3) tesla in the sensor frame."""

    t: FloatArray
    field: FloatArray

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        self.field = _as2d(self.field, 3)

    def __len__(self) -> int:
        return len(self.t)

    def slice(self, s: slice | NDArray[np.bool_] | NDArray[np.int64]) -> MagSamples:
        return MagSamples(self.t[s], self.field[s])


@dataclass(frozen=True)
class Marker:
    """One above-ground-marker passage.

    name: marker name (``agm_03``); t: passage time, s; lat, lon: rad (WGS84); alt: ellipsoidal
    height of the pipe centreline at the marker, m; sigma_enu: one-sigma survey uncertainty
    (east, north, up), m.
    """

    name: str
    t: float
    lat: float
    lon: float
    alt: float
    sigma_enu: tuple[float, float, float] = (0.02, 0.02, 0.02)


def empty_imu() -> ImuSamples:
    return ImuSamples(np.empty(0), np.empty((0, 3)), np.empty((0, 3)))


def empty_odometer() -> OdometerSamples:
    return OdometerSamples(np.empty(0), np.empty(0), np.empty(0))


def empty_mag() -> MagSamples:
    return MagSamples(np.empty(0), np.empty((0, 3)))


@dataclass
class SensorLog:
    """A whole recorded run in memory (or one chunk of it), each topic sorted by time."""

    imu: ImuSamples = field(default_factory=empty_imu)
    odometer: OdometerSamples = field(default_factory=empty_odometer)
    mag: MagSamples = field(default_factory=empty_mag)
    markers: list[Marker] = field(default_factory=list)

    def to_base_link(self, r_base_imu: FloatArray) -> SensorLog:
        """Rotate IMU and magnetometer vectors from imu_link into base_link.

        r_base_imu: (3, 3) rotation matrix taking imu_link vectors into base_link.
        """
        r = np.asarray(r_base_imu, dtype=np.float64)
        return SensorLog(
            imu=ImuSamples(self.imu.t, self.imu.gyro @ r.T, self.imu.accel @ r.T),
            odometer=self.odometer,
            mag=MagSamples(self.mag.t, self.mag.field @ r.T),
            markers=list(self.markers),
        )


def markers_sorted(markers: Sequence[Marker]) -> list[Marker]:
    """Markers in passage-time order; markers without a passage time (NaN: surveyed, not yet
    passed) follow in their given order."""
    return sorted(markers, key=lambda m: (math.isnan(m.t), 0.0 if math.isnan(m.t) else m.t))


@dataclass
class Trajectory:
    """A navigation trajectory (truth from the simulator, or an estimate), sampled at times t.

    t: (N,) s; lat, lon: (N,) rad; h: (N,) m ellipsoidal; vel_n: (N, 3) m/s ENU;
    quat_nb: (N, 4) [x, y, z, w] rotating base_link into ENU; distance: (N,) m along the pipe
    centreline (truth) or calibrated odometer chainage (estimate);
    sigma_enu: optional (N, 3) one-sigma position uncertainty, m;
    sigma_att: optional (N, 3) one-sigma attitude uncertainty about E, N, U axes, rad;
    cov_pose: optional (N, 6, 6) full pose covariance over [E, N, U (m), rotation about E, N,
    U (rad)] (what nav_msgs/Odometry carries), when known.
    """

    t: FloatArray
    lat: FloatArray
    lon: FloatArray
    h: FloatArray
    vel_n: FloatArray
    quat_nb: FloatArray
    distance: FloatArray
    sigma_enu: FloatArray | None = None
    sigma_att: FloatArray | None = None
    cov_pose: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True)
class Datum:
    """Geodetic origin of the ``map`` ENU frame: lat, lon rad (WGS84), alt m (ellipsoidal)."""

    lat: float
    lon: float
    alt: float
