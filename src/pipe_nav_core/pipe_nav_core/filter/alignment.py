"""The static alignment: the filter's initial state and covariance from the initial rest.

- :func:`rest_window`: the IMU samples of the initial rest, once all of it is in;
- :func:`align`: the aligned state, its covariance (:func:`initial_covariance`) and the
  initial heading's source, from those samples;
- :func:`level`: roll and pitch from the mean specific force at rest (seed 001 eq. 11-12 in
  base_link FLU axes);
- :func:`gyro_bias_at_rest`: gyro bias = mean rate minus the Earth rate seen in the body;
- :func:`marker_bearing`: azimuth from the first to the second marker (seed 000);
- :func:`mag_azimuth`: azimuth from a levelled magnetometer reading and the declination;
All angles rad; azimuth clockwise from true north.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import AUTO_GRADE, NavConfig
from pipe_nav_core.filter.anchoring import FREE_HEADING_SIGMA, UNKNOWN_HEADING_VARIANCE, FreeHeading
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.model import imu_noise as imu_model
from pipe_nav_core.model.measurements.section_direction import RESTART_SIGMA
from pipe_nav_core.model.sensors import ImuSpec
from pipe_nav_core.model.state import Layout, NavState
from pipe_nav_core.types import MagSamples, Marker, OdometerSamples

if TYPE_CHECKING:
    from pipe_nav_core.filter.navigator import PassOptions

Array = NDArray[np.float64]

ALIGN_WAIT_S = 5.0  # after motion starts, wait this long for the first marker before starting
STATIC_MOVE_M = 0.005  # odometer change that ends the initial rest


def level(f_mean_b: Array) -> tuple[float, float]:
    """(roll, pitch) rad from the mean specific force (m/s^2, base_link) of a pig at rest."""
    f = np.asarray(f_mean_b, dtype=np.float64)
    pitch = float(np.arctan2(f[0], np.hypot(f[1], f[2])))
    roll = float(np.arctan2(f[1], f[2]))
    return roll, pitch


def gyro_bias_at_rest(
    gyro_mean_b: Array, c_nb: Array, lat: float, earth_sign: float = 1.0
) -> Array:
    """Gyro bias (rad/s, base_link) from the mean rate at rest and the attitude C_nb
    (earth_sign -1 for time-reversed data)."""
    w_ie = earth_sign * earth.earth_rate_n(lat)
    return np.asarray(gyro_mean_b, dtype=np.float64) - c_nb.T @ w_ie


def enu_of(marker: Marker, ref: Marker) -> Array:
    """ENU position (m) of marker relative to ref."""
    return earth.geodetic_to_enu(marker.lat, marker.lon, marker.alt, ref.lat, ref.lon, ref.alt)


def marker_bearing(first: Marker, second: Marker) -> tuple[float, float]:
    """(azimuth rad, horizontal distance m) from the first marker to the second."""
    d = enu_of(second, first)
    return float(np.mod(np.arctan2(d[0], d[1]), 2 * np.pi)), float(np.hypot(d[0], d[1]))


def mag_azimuth(field_b: Array, roll: float, pitch: float, declination: float) -> float:
    """Azimuth (rad) of base_link x from a magnetometer reading (base_link) at known roll/pitch."""
    c0 = att.dcm_from_euler(roll, pitch, 0.0)
    m = c0 @ np.asarray(field_b, dtype=np.float64)
    az_field = np.arctan2(m[0], m[1])
    return float(np.mod(declination - az_field, 2 * np.pi))


def rest_window(
    imu_t: Array,
    odo: OdometerSamples,
    first: Marker | None,
    static_alignment_s: float,
    horizon: float,
) -> NDArray[np.intp] | None:
    """Indices of the IMU samples (stamps imu_t, s) of the initial rest, or None until all of
    it is in (horizon: stamp time up to which all data are in). The rest ends at the first
    odometer move (odo), the first marker passage or static_alignment_s (s) after the first
    sample; without a marker it waits ALIGN_WAIT_S after the move for one (the start
    position)."""
    t = imu_t
    if len(t) < 2:
        return None
    o = odo
    moved = np.nonzero(np.abs(o.distance - o.distance[0]) > STATIC_MOVE_M)[0] if len(o) else []
    t_move = float(o.t[moved[0]]) if len(moved) else math.inf
    if first is not None and first.t > t[0]:
        t_move = min(t_move, first.t)
    static_end = min(t_move, t[0] + max(static_alignment_s, 0.1) + 1e-9)
    if t[-1] < static_end or horizon < static_end:
        return None
    if first is None and horizon < t_move + ALIGN_WAIT_S:
        return None
    sel = t <= static_end
    if sel.sum() < 2:
        sel[:2] = True
    return np.nonzero(sel)[0]


@dataclass
class Aligned:
    """The static alignment's result: the state and its covariance P0 (n, n) (layout), the
    initial azimuth (rad), the part of the heading prior kept outside P0 (or None), the IMU
    model (chosen at the rest with imu_grade auto: choice) and the magnetic reference
    (field magnitude T, inclination rad) when a magnetometer was read at the rest."""

    state: NavState
    P0: Array
    azimuth: float
    free_heading: FreeHeading | None
    imu_spec: ImuSpec
    imu_choice: imu_model.ImuModelChoice | None
    mag_ref: tuple[float, float] | None


def align(
    cfg: NavConfig,
    layout: Layout,
    rest: tuple[Array, Array, Array],
    mag: MagSamples,
    first: Marker | None,
    survey: Sequence[Marker],
    options: PassOptions,
    anchored: bool,
    declared_imu_noise: dict[str, list[float]] | None,
    odometer_resolution: Callable[[float], float],
) -> Aligned:
    """Level from the mean specific force, heading from its source (the survey's first two
    markers, the magnetometer, the configuration, or options.initial / initial_azimuth), gyro
    bias from the mean rate, position at the first marker. rest: the initial rest's IMU
    samples (times s, rates rad/s, specific forces m/s^2, base_link); mag: the buffered
    magnetometer samples (T, base_link); anchored: the heading needs no re-anchoring;
    odometer_resolution(t): the encoder resolution (m) at t (s)."""
    t, gyro, accel = rest
    imu_choice = None
    spec = cfg.imu_spec()
    if cfg.imu_grade == AUTO_GRADE:
        imu_choice = imu_model.choose_at_rest(t, gyro, accel, cfg, declared_imu_noise)
        spec = imu_choice.config.imu_spec()
    earth_sign = options.earth_sign
    dts = np.diff(t)
    w = np.r_[dts[0], dts]
    f_mean = np.average(accel, axis=0, weights=w)
    g_mean = np.average(gyro, axis=0, weights=w)
    t_static = float(w.sum())
    roll, pitch = level(f_mean)
    lat, lon, h = (first.lat, first.lon, first.alt) if first else (0.0, 0.0, 0.0)
    azimuth, az_sigma = cfg.initial_azimuth, cfg.initial_heading_sigma
    markers_source = cfg.heading_source == "markers"
    bearing = markers_source and len(survey) >= 2
    if bearing:
        azimuth, _ = marker_bearing(survey[0], survey[1])
        if earth_sign < 0:  # reversed time: the pig backs along the bearing
            azimuth = float(np.mod(azimuth + np.pi, 2 * np.pi))
    mag_ref = None
    mag_sel = mag.t <= t[-1]
    if mag_sel.any():
        m_mean = mag.field[mag_sel].mean(axis=0)
        mag_ref = (float(np.linalg.norm(m_mean)), 0.0)
        if cfg.heading_source == "magnetometer":
            azimuth = mag_azimuth(m_mean, roll, pitch, cfg.mag_declination)
            az_sigma = cfg.mag_heading_sigma
    initial = options.initial
    if initial is not None:
        roll, pitch, azimuth = (float(x) for x in att.euler_from_dcm(initial.c_nb))
    if options.initial_azimuth is not None:
        azimuth = float(options.initial_azimuth)
    c = att.dcm_from_euler(roll, pitch, azimuth)
    if mag_ref is not None:
        m_n = c @ mag.field[mag_sel].mean(axis=0)
        mag_ref = (mag_ref[0], float(np.arctan2(-m_n[2], np.hypot(m_n[0], m_n[1]))))
    bg = gyro_bias_at_rest(g_mean, c, lat, earth_sign)
    s = NavState(
        t=float(t[-1]),
        lat=lat,
        lon=lon,
        h=h,
        vel_n=np.zeros(3),
        q_nb=att.quat_from_dcm(c),
        bg=bg,
        ba=np.zeros(3),
    )
    if initial is not None:
        s.bg, s.ba = initial.bg.copy(), initial.ba.copy()
        s.k, s.bore = initial.k, initial.bore.copy()
        s.gm = initial.gm.copy()
        s.am = initial.am.copy()
    s.distance = 0.0
    free = not anchored if options.free_heading is None else options.free_heading
    # markers as the source but no bearing, and no azimuth given in its place
    unknown = markers_source and not bearing and initial is None and options.initial_azimuth is None
    free_heading = None
    if free and not cfg.mag_update and (unknown or az_sigma > FREE_HEADING_SIGMA):
        var = UNKNOWN_HEADING_VARIANCE if unknown else az_sigma**2 - FREE_HEADING_SIGMA**2
        free_heading = FreeHeading(var, s.lat, s.lon, s.h, unknown=unknown)
        az_sigma = FREE_HEADING_SIGMA
    P0 = initial_covariance(
        cfg, layout, spec, s, t_static, az_sigma, earth_sign,
        rest_bias=initial is None and t_static >= 0.5, gyrocompass=anchored, first=first,
        odometer_resolution=odometer_resolution,
    )  # fmt: skip
    return Aligned(s, P0, float(azimuth), free_heading, spec, imu_choice, mag_ref)


def initial_covariance(
    cfg: NavConfig,
    lay: Layout,
    imu: ImuSpec,
    s: NavState,
    t_static: float,
    az_sigma: float,
    earth_sign: float,
    *,
    rest_bias: bool,
    gyrocompass: bool,
    first: Marker | None,
    odometer_resolution: Callable[[float], float],
) -> Array:
    """P0 (n, n) (layout lay) of the state s aligned over t_static s of rest, with the
    couplings static alignment creates: levelled tilt absorbs the horizontal accelerometer
    error at rest (bias, and scale factor and misalignment times gravity), and, when the gyro
    bias was measured at the rest (rest_bias), it absorbs the Earth rate error of the heading
    (az_sigma rad; its vertical component only with gyrocompass, that is once the heading
    is anchored: epoch.py, heading_free). Position sigma: the first marker's survey."""
    n = lay.n
    P = np.zeros((n, n))
    c = s.c_nb
    g = earth.gravity(s.lat, s.h)
    ba_var = imu.accel_turn_on_bias**2 + imu.accel_bias_instability**2
    bg_var = imu.gyro_turn_on_bias**2 + imu.gyro_bias_instability**2
    # accelerometer error sources and their equivalent body bias at rest: b = B src
    src = np.arange(lay.ba.start, lay.ba.stop)
    var = [ba_var] * 3
    B = np.eye(3)
    if lay.am is not None:
        f_rest = c.T @ np.array([0.0, 0.0, g])
        src = np.r_[src, np.arange(lay.am.start, lay.am.stop)]
        am_var = np.full((3, 3), imu.accel_misalignment**2)
        np.fill_diagonal(am_var, imu.accel_scale_factor**2)
        var += list(np.maximum(am_var.reshape(9), 1e-12))
        B = np.hstack([B, np.kron(np.eye(3), f_rest[None, :])])
    P_src = np.diag(var)
    P[np.ix_(src, src)] = P_src
    J = np.zeros((3, 3))  # phi = J b (+ levelling noise)
    J[0] = -c[1] / g
    J[1] = c[0] / g
    tilt_var = cfg.initial_tilt_sigma**2 + imu.accel_vrw**2 / max(t_static, 0.1) / g**2
    JB = J @ B
    P_att = JB @ P_src @ JB.T + np.diag([tilt_var, tilt_var, az_sigma**2])
    P[lay.att, lay.att] = P_att
    P[lay.att, src] = JB @ P_src
    P[src, lay.att] = P[lay.att, src].T
    if not rest_bias:
        P[lay.bg, lay.bg] = np.eye(3) * bg_var
    else:
        G = -c.T @ att.skew(earth_sign * earth.earth_rate_n(s.lat))
        if not gyrocompass:
            G[:, 2] = 0.0  # no gyrocompassing before the anchoring (epoch.py, heading_free)
        noise = imu.gyro_arw**2 / t_static + imu.gyro_bias_instability**2
        P[lay.bg, lay.bg] = G @ P_att @ G.T + np.eye(3) * noise
        P[lay.bg, lay.att] = G @ P_att
        P[lay.att, lay.bg] = P[lay.bg, lay.att].T
        P[lay.bg, src] = G @ P[lay.att, src]
        P[src, lay.bg] = P[lay.bg, src].T
    if lay.vel is not None:
        P[lay.vel, lay.vel] = np.eye(3) * cfg.zupt_sigma**2
    sig = first.sigma_enu if first else (1e3, 1e3, 1e3)
    P[lay.pos, lay.pos] = np.diag(np.maximum(np.square(sig), cfg.initial_position_sigma**2))
    P[lay.k, lay.k] = cfg.odometer_scale_sigma**2
    P[lay.bore, lay.bore] = np.eye(2) * cfg.boresight_sigma**2
    if lay.odoq is not None:
        P[lay.odoq, lay.odoq] = np.eye(2) * odometer_resolution(s.t) ** 2 / 12.0
    if lay.gm is not None:
        gm_var = np.full((3, 3), imu.gyro_misalignment**2)
        np.fill_diagonal(gm_var, imu.gyro_scale_factor**2)
        P[lay.gm, lay.gm] = np.diag(np.maximum(gm_var.reshape(9), 1e-12))
    if lay.dir is not None:  # no section yet: free until the first one restarts it
        P[lay.dir, lay.dir] = np.eye(2) * RESTART_SIGMA**2
    return P
