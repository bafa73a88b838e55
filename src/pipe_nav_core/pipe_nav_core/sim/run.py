"""One simulated pig run: :func:`simulate` turns a :class:`Scenario` and a seed into a sensor log
(as recorded in a bag) and the truth it came from.

Random streams: the seed feeds a ``numpy.random.SeedSequence`` whose children drive, separately,
the motion (speed and roll), the IMU errors, the odometer, the magnetometer and the marker
timing; the pipe itself (field bends, girth welds, the markers' survey errors) depends only on
the scenario, so every run through a pipe shares one survey. No global random state.
The IMU is generated in time chunks with stateful error processes, so the result does not depend
on the chunk size and memory stays bounded (a few arrays the size of the output).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.sim.geometry import PipeGeometry
from pipe_nav_core.sim.imu import ImuErrorModel, TriadErrors
from pipe_nav_core.sim.kinematics import (
    evaluate,
    interval_means,
    lobatto_times,
    quat_from_angles,
    short_feature_intervals,
    sub_interval_means,
    sub_interval_times,
)
from pipe_nav_core.sim.magnetometer import WeldField, earth_field_enu, magnetometer_reading
from pipe_nav_core.sim.markers import make_markers
from pipe_nav_core.sim.motion import PigMotion, build_roll_profiles, build_speed_profile
from pipe_nav_core.sim.odometer import SlipEpisode, draw_slips, odometer_reading
from pipe_nav_core.sim.scenarios import Scenario, get_scenario
from pipe_nav_core.sim.weld_bump import weld_bump_accel, weld_passage_times
from pipe_nav_core.types import (
    Datum,
    ImuSamples,
    MagSamples,
    Marker,
    SensorLog,
    Trajectory,
    empty_mag,
)

FloatArray = NDArray[np.float64]


@dataclass
class SimRun:
    """A simulated run.

    scenario, seed: what was simulated. log: the sensor data as recorded (``/imu/data`` in
    imu_link, ``/odom/wheel`` raw cumulative distance and driver speed, ``/imu/mag`` in imu_link
    (empty when the scenario has none), markers with noisy passage times and survey positions).
    truth: at the IMU sample times, true centreline position, ENU velocity, q_nb of base_link and
    the true centreline chainage in ``distance``. datum: true position of the launch trap.

    The remaining fields are truth for diagnostics and tests; an estimator must not use them:
    markers_true (exact times and positions), marker_chainages (m), wall_distance (m, true wall
    distance at log.odometer.t), odometer_scale (true scale error), slips, imu_errors (realised
    constant errors of the gyro and accelerometer triads, imu_link), bias_t / gyro_bias /
    accel_bias (total bias, turn-on plus Gauss-Markov, in imu_link, about 1 Hz), t_move and
    t_arrive (s, when the pig leaves the launch trap and reaches the receive trap), geometry and
    motion (the exact functions behind everything), r_base_imu (imu_link -> base_link),
    imu_rate_hz (Hz); welds: the girth welds' true chainages (m, increasing; the pipe's, drawn
    whether or not the run has a magnetometer) and weld_field (their magnetic anomalies).
    """

    scenario: Scenario
    seed: int
    log: SensorLog
    truth: Trajectory
    datum: Datum
    markers_true: list[Marker] = field(default_factory=list)
    marker_chainages: FloatArray = field(default_factory=lambda: np.empty(0))
    wall_distance: FloatArray = field(default_factory=lambda: np.empty(0))
    odometer_scale: float = 0.0
    slips: list[SlipEpisode] = field(default_factory=list)
    imu_errors: dict[str, TriadErrors] = field(default_factory=dict)
    bias_t: FloatArray = field(default_factory=lambda: np.empty(0))
    gyro_bias: FloatArray = field(default_factory=lambda: np.empty((0, 3)))
    accel_bias: FloatArray = field(default_factory=lambda: np.empty((0, 3)))
    t_move: float = 0.0
    t_arrive: float = 0.0
    geometry: PipeGeometry | None = None
    motion: PigMotion | None = None
    r_base_imu: FloatArray = field(default_factory=lambda: np.eye(3))
    imu_rate_hz: float = 0.0
    welds: FloatArray = field(default_factory=lambda: np.empty(0))
    weld_field: WeldField | None = None

    def imu_noise_variance(self) -> tuple[float, float]:
        """Per-sample white-noise variance of (gyro (rad/s)^2, accel (m/s^2)^2) as the data sheet
        of the simulated grade states it (density^2 / dt), for the covariances of /imu/data."""
        spec = self.scenario.imu_error_spec()
        return spec.gyro_arw**2 * self.imu_rate_hz, spec.accel_vrw**2 * self.imu_rate_hz


def mount_matrix(rpy: tuple[float, float, float]) -> FloatArray:
    """Rotation imu_link -> base_link from (roll, pitch, yaw) rad as Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr = math.cos(r), math.sin(r)
    cp, sp = math.cos(p), math.sin(p)
    cy, sy = math.cos(y), math.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def build_motion(scn: Scenario, rng: np.random.Generator) -> PigMotion:
    """The pig's motion for one run (speed and roll drawn from rng), times in s from scn.t0."""
    t_begin = float(scn.t0)
    t_move = t_begin + scn.static_start
    speed = build_speed_profile(
        scn.total_length, t_move, scn.speed_params(), scn.scaled_stops(), rng
    )
    t_arrive = speed.end
    t_end = t_arrive + scn.static_end
    wander, pulses = build_roll_profiles(
        scn.total_length,
        speed,
        scn.speed,
        scn.roll_wander,
        scn.roll_wander_interval,
        scn.scaled_roll_turns(),
        rng,
    )
    return PigMotion(speed, scn.roll0, [wander, pulses], scn.total_length, t_begin, t_end)


def _hermite(t: FloatArray, tk: FloatArray, y: FloatArray, dy: FloatArray) -> FloatArray:
    """Cubic Hermite interpolation of y (with derivative dy) sampled at sorted tk."""
    k = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 2)
    h = tk[k + 1] - tk[k]
    x = (t - tk[k]) / h
    x2, x3 = x * x, x * x * x
    return (
        (2 * x3 - 3 * x2 + 1) * y[k]
        + (x3 - 2 * x2 + x) * h * dy[k]
        + (-2 * x3 + 3 * x2) * y[k + 1]
        + (x3 - x2) * h * dy[k + 1]
    )


def simulate(
    scenario: str | Scenario,
    seed: int = 0,
    *,
    imu_rate_hz: float | None = None,
    truth_every: int = 1,
    chunk_size: int = 50_000,
) -> SimRun:
    """Simulate one run of ``scenario`` (a name or a Scenario) with random ``seed``.

    imu_rate_hz: override of the scenario's IMU rate (Hz). truth_every: keep the truth at every
    k-th IMU sample only (1 = all; use 10 or more for 100 km runs to save memory). chunk_size:
    IMU samples generated per step (affects memory only, not the result).
    Returns a :class:`SimRun`; times are s, angles rad, positions WGS84 (rad, rad, m).
    """
    scn = get_scenario(scenario) if isinstance(scenario, str) else scenario
    if not isinstance(scn, Scenario):
        raise TypeError(f"scenario must be a name or a Scenario, not {type(scenario).__name__}")
    rate = float(imu_rate_hz) if imu_rate_hz is not None else scn.imu_rate_hz
    if not rate > 0.0:
        raise ValueError(f"imu_rate_hz must be positive, not {rate}")
    truth_every = max(1, int(truth_every))
    chunk = max(truth_every, (int(chunk_size) // truth_every) * truth_every)
    dt = 1.0 / rate

    ss = np.random.SeedSequence(int(seed))
    r_motion, r_imu, r_odo, r_mag, r_mark = (np.random.default_rng(c) for c in ss.spawn(5))

    geometry = scn.build_geometry()
    motion = build_motion(scn, r_motion)
    r_bi = mount_matrix(scn.imu_mount_rpy)
    spec = scn.imu_error_spec()
    errors = ImuErrorModel(spec, dt, r_imu)
    lever = np.asarray(scn.lever_arm(), dtype=np.float64)

    n = int(math.floor((motion.t_end - motion.t_begin) * rate + 1e-9)) + 1
    t_imu = motion.t_begin + np.arange(n) * dt
    gyro = np.empty((n, 3))
    accel = np.empty((n, 3))
    n_truth = (n + truth_every - 1) // truth_every
    tr_t = np.empty(n_truth)
    tr_lat = np.empty(n_truth)
    tr_lon = np.empty(n_truth)
    tr_h = np.empty(n_truth)
    tr_v = np.empty((n_truth, 3))
    tr_q = np.empty((n_truth, 4))
    tr_s = np.empty(n_truth)
    wall = np.empty(n)
    wall_rate = np.empty(n)
    bias_every = max(1, int(round(rate)))
    b_idx: list[FloatArray] = []
    b_g: list[FloatArray] = []
    b_a: list[FloatArray] = []
    w_carry = 0.0

    spans = geometry.feature_spans()
    for i0 in range(0, n, chunk):
        i1 = min(n, i0 + chunk)
        tn = lobatto_times(t_imu[i0:i1], dt, t_imu[i0 - 1] if i0 > 0 else None)
        st = evaluate(geometry, motion, tn)
        w_ib = st.omega_ib_b()
        f_b = st.specific_force_b()
        wall_speed = st.wall_speed(lever)
        g_mean = interval_means(w_ib)
        f_mean = interval_means(f_b)
        inc = interval_means(wall_speed) * dt
        short = short_feature_intervals(spans, st.s[0::4])
        if len(short):  # a feature too short for the nodes: finer sub-intervals there
            fine = evaluate(geometry, motion, sub_interval_times(tn, short))
            g_mean[short] = sub_interval_means(fine.omega_ib_b(), len(short))
            f_mean[short] = sub_interval_means(fine.specific_force_b(), len(short))
            inc[short] = sub_interval_means(fine.wall_speed(lever), len(short)) * dt
        if i0 == 0:
            inc[0] = 0.0  # the distance is counted from the first sample
        wall[i0:i1] = np.cumsum(np.concatenate([[w_carry], inc]))[1:]
        w_carry = float(wall[i1 - 1])
        wall_rate[i0:i1] = wall_speed[4::4]
        gm, am, gb, ab = errors.apply(g_mean @ r_bi, f_mean @ r_bi)
        gyro[i0:i1] = gm
        accel[i0:i1] = am
        keep = np.arange(i0, i1)
        kb = keep % bias_every == 0
        b_idx.append(keep[kb])
        b_g.append(gb[kb] + errors.gyro.errors.turn_on_bias)
        b_a.append(ab[kb] + errors.accel.errors.turn_on_bias)
        sel = np.nonzero(keep % truth_every == 0)[0]
        j0 = i0 // truth_every
        j1 = j0 + len(sel)
        e = 4 * sel + 4  # endpoint node of each interval
        tr_t[j0:j1] = tn[e]
        tr_lat[j0:j1] = st.lat[e]
        tr_lon[j0:j1] = st.lon[e]
        tr_h[j0:j1] = st.h[e]
        tr_v[j0:j1] = st.v_n[e]
        tr_s[j0:j1] = st.s[e]
        tr_q[j0:j1] = quat_from_angles(st.roll[e], st.pitch[e], st.azimuth[e])
        del st, w_ib, f_b, wall_speed, tn

    weld_field = _weld_field(scn)
    if scn.weld_bump_height > 0.0 and len(weld_field.welds):
        t_w = weld_passage_times(weld_field.welds, tr_t, tr_s, float(lever[0]))
        bump = weld_bump_accel(t_imu, t_w, scn.weld_bump_height, scn.weld_bump_duration)
        accel += bump[:, None] * r_bi[2][None, :]  # base_link z in imu_link: row 2 of R_bi
    imu = ImuSamples(t_imu, gyro, accel)
    truth = Trajectory(tr_t, tr_lat, tr_lon, tr_h, tr_v, tr_q, tr_s)

    # Odometer.
    n_odo = int(math.floor((motion.t_end - motion.t_begin) * scn.odo_rate_hz + 1e-9)) + 1
    t_odo = motion.t_begin + np.arange(n_odo) / scn.odo_rate_hz
    wall_odo = _hermite(t_odo, t_imu, wall, wall_rate) if n > 1 else np.zeros(n_odo)
    wall_odo = wall_odo - wall_odo[0]
    del wall, wall_rate
    odo_scale = float(r_odo.standard_normal() * scn.odo_scale_sigma)
    slips = draw_slips(
        r_odo, motion.t_move, motion.t_arrive, scn.odo_slip_interval, scn.odo_slip_duration
    )
    odometer = odometer_reading(
        t_odo,
        wall_odo,
        scale_error=odo_scale,
        tick=scn.odo_tick,
        slips=slips,
        speed_window=scn.odo_speed_window,
    )

    # Magnetometer.
    mag = empty_mag()
    if scn.mag_enabled:
        n_mag = int(math.floor((motion.t_end - motion.t_begin) * scn.mag_rate_hz + 1e-9)) + 1
        t_mag = motion.t_begin + np.arange(n_mag) / scn.mag_rate_hz
        welds = weld_field
        b_field = earth_field_enu(scn.mag_declination, scn.mag_inclination, scn.mag_field)
        parts = []
        for k0 in range(0, n_mag, chunk):
            sm = evaluate(geometry, motion, t_mag[k0 : k0 + chunk])
            parts.append(
                magnetometer_reading(
                    sm.c_nb,
                    sm.s,
                    b_field,
                    scn.mag_attenuation,
                    welds,
                    r_bi,
                    np.asarray(scn.mag_hard_iron),
                    scn.mag_noise,
                    r_mag,
                )
            )
        mag = MagSamples(t_mag, np.concatenate(parts) if parts else np.empty((0, 3)))

    # Markers.
    chain = scn.marker_chainage_list()
    noisy, true = make_markers(
        geometry,
        motion,
        chain,
        scn.marker_time_sigma,
        scn.survey_sigma_h,
        scn.survey_sigma_v,
        r_mark,
        scn.pipe_seed,
    )
    lat0, lon0, h0 = geometry.position(0.0)
    datum = Datum(float(lat0), float(lon0), float(h0))
    log = SensorLog(imu=imu, odometer=odometer, mag=mag, markers=noisy)
    bi = np.concatenate(b_idx) if b_idx else np.empty(0, dtype=np.int64)
    return SimRun(
        scenario=scn,
        seed=int(seed),
        log=log,
        truth=truth,
        datum=datum,
        markers_true=true,
        marker_chainages=chain,
        wall_distance=wall_odo,
        odometer_scale=odo_scale,
        slips=slips,
        imu_errors={"gyro": errors.gyro.errors, "accel": errors.accel.errors},
        bias_t=t_imu[bi],
        gyro_bias=np.concatenate(b_g) if b_g else np.empty((0, 3)),
        accel_bias=np.concatenate(b_a) if b_a else np.empty((0, 3)),
        t_move=motion.t_move,
        t_arrive=motion.t_arrive,
        geometry=geometry,
        motion=motion,
        r_base_imu=r_bi,
        imu_rate_hz=rate,
        welds=weld_field.welds.copy(),
        weld_field=weld_field,
    )


def _weld_field(scn: Scenario) -> WeldField:
    """The pipe's girth welds and their anomalies (depend on the pipe only, not the seed)."""
    return WeldField.draw(
        np.random.default_rng([scn.pipe_seed, 7002]),
        scn.total_length,
        scn.weld_spacing,
        scn.weld_anomaly,
        scn.weld_width if scn.weld_width is not None else scn.pipe_diameter,
    )


__all__ = ["SimRun", "build_motion", "mount_matrix", "simulate"]
