"""The navigation engine: one object used identically by the live node, the bag replay and the
offline smoother.

Feed samples (``push_*`` one at a time in any order within the reorder window, or
:meth:`Navigator.run` with a time-sorted :class:`~pipe_nav_core.types.SensorLog`), collect
:class:`NavEstimate` s (one per filter epoch) with :meth:`Navigator.poll`. With ``record=True``
the engine keeps what the smoothers need (:class:`Recording`).

Processing: static alignment -> per epoch (``filter_rate_hz``): mechanize the IMU samples
(INS or DR), propagate the covariance, then gated updates: odometer speed + non-holonomic
constraint (INS), zero velocity and zero rate at stops, gravity tilt, magnetic heading, marker
fixes, with the heading re-anchored at the second marker when it comes from the markers.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from . import alignment, earth
from . import attitude as att
from . import measurements as meas
from .config import NavConfig
from .kalman import ErrorStateKF, chi2_threshold
from .mechanization import BlockResult, Carry, dr_block, ins_block
from .process import continuous_noise, discretize, integrated_system_matrix
from .state import NavState, layout_for
from .stream import ReorderBuffer
from .types import (
    Datum,
    ImuSamples,
    MagSamples,
    Marker,
    OdometerSamples,
    SensorLog,
    markers_sorted,
)

Array = NDArray[np.float64]

ODOMETER_TIMEOUT_S = 1.0  # an epoch waits at most this long (stamp time) for odometer coverage
ALIGN_WAIT_S = 5.0  # after motion starts, wait this long for the first marker before starting
STATIC_MOVE_M = 0.005  # odometer change that ends the initial rest


@dataclass
class NavEstimate:
    """Estimate at the end of one filter epoch.

    t s; lat, lon rad; h m; vel_n (3,) m/s ENU; quat_nb (4,) [x,y,z,w] base_link->ENU;
    omega_b (3,) rad/s bias-corrected body rate; cov_pose (6, 6) over [E, N, U (m),
    rotation about E, N, U (rad)]; cov_vel_n (3, 3) (m/s)^2; distance m calibrated chainage;
    status: "static" or "moving".
    """

    t: float
    lat: float
    lon: float
    h: float
    vel_n: Array
    quat_nb: Array
    omega_b: Array
    cov_pose: Array
    cov_vel_n: Array
    distance: float
    status: str


@dataclass
class Recording:
    """What the smoothers need from a forward pass.

    Per epoch k (k = 0 is the alignment): t; the filter's estimate after the update
    (``states``); the linearization point ``lin`` (the estimate itself for the ordinary EKF,
    the reference state when the filter runs about a reference trajectory); the filter's mean
    error state relative to it ``x_upd`` (zero for the EKF); the predicted and updated
    covariances; Phi from k-1 to k; ``dx`` = updated minus predicted mean error state (what an
    RTS smoother carries back); ``end_offset`` = lin (-) the nominal at the end of the block
    (the correction that moves the per-sample nominal onto the linearization point).
    Per IMU sample: t, raw odometer distance (m), nominal lat, lon, h, q_nb and the epoch
    whose block the sample belongs to (the block of epoch k starts at lin[k - 1]).
    """

    t: list[float] = field(default_factory=list)
    states: list[NavState] = field(default_factory=list)
    lin: list[NavState] = field(default_factory=list)
    x_upd: list[Array] = field(default_factory=list)
    P_pred: list[Array] = field(default_factory=list)
    P_upd: list[Array] = field(default_factory=list)
    phi: list[Array] = field(default_factory=list)
    dx: list[Array] = field(default_factory=list)
    end_offset: list[Array] = field(default_factory=list)
    s_t: list[Array] = field(default_factory=list)
    s_odo: list[Array] = field(default_factory=list)
    s_lat: list[Array] = field(default_factory=list)
    s_lon: list[Array] = field(default_factory=list)
    s_h: list[Array] = field(default_factory=list)
    s_q: list[Array] = field(default_factory=list)
    s_epoch: list[Array] = field(default_factory=list)
    marker_residuals: dict[str, Array] = field(default_factory=dict)


def mount_rotation(rpy: Sequence[float]) -> Array:
    """Rotation imu_link -> base_link from (roll, pitch, yaw) rad: Rz(yaw) Ry(pitch) Rx(roll)."""
    return Rotation.from_euler("xyz", list(rpy)).as_matrix()


class Navigator:
    """The online estimator (see module docstring).

    config: estimator settings; survey: surveyed markers known in advance (their passage times
    may be unknown); record: keep the smoother's data; reverse: the data are time-reversed (the
    backward filter of the two-filter smoother); initial: a state whose attitude azimuth,
    biases, odometer scale and boresight replace the static-alignment values (the offline
    smoother's re-linearization pass); epoch_times: force the epoch ends to the first IMU
    samples at or after these times instead of filter_rate_hz and marker passages (the backward
    filter uses the forward filter's epochs); odometer_exclude: (N, 2) time intervals whose
    odometer speed is not used (slips found by a previous smoothing pass); reference: a
    trajectory (one NavState per epoch, from the alignment on, at the epoch times of an earlier
    pass of this engine over the same data) about which every Jacobian, transition and
    measurement residual is linearized instead of about the filter's own estimate; the prior
    stays the static alignment's and the filter carries its mean error relative to the
    reference. Smoothing such a pass and feeding the result back as the next reference is one
    Gauss-Newton step of the batch problem (iterated smoother, :mod:`pipe_nav_core.smoother`);
    initial_azimuth: rad, replaces the initial heading of the configured source (the smoother
    iterates the re-anchoring at the second marker with it).

    Jacobians that couple attitude and velocity are evaluated at a first-estimate velocity
    (the predicted one, zero when stopped, or the reference's) so that a rotation of the whole
    solution about the vertical stays unobservable between markers, as it is: evaluating them
    at the freshly corrected velocity makes an EKF believe it learns its heading from odometer
    and zero-velocity noise.
    """

    def __init__(
        self,
        config: NavConfig,
        survey: Sequence[Marker] = (),
        *,
        record: bool = False,
        reverse: bool = False,
        initial: NavState | None = None,
        epoch_times: Array | None = None,
        odometer_exclude: Array | None = None,
        reference: Sequence[NavState] | None = None,
        initial_azimuth: float | None = None,
    ) -> None:
        config.validate()
        self.cfg = config
        self.layout = layout_for(config)
        pose = [*range(self.layout.pos.start, self.layout.pos.stop)]
        pose += range(self.layout.att.start, self.layout.att.stop)
        self._pose_ix = np.ix_(pose, pose)  # [position, attitude] rows/columns of P
        self.imu_spec = config.imu_spec()
        self.r_base_imu = mount_rotation(config.imu_mount_rpy)
        self.earth_sign = -1.0 if reverse else 1.0
        self.survey = markers_sorted(survey)
        self.record = record
        self.initial = initial
        self.odometer_exclude = (
            np.zeros((0, 2)) if odometer_exclude is None else np.asarray(odometer_exclude, float)
        )
        self.epoch_times = None if epoch_times is None else np.sort(np.asarray(epoch_times, float))
        self.reference = list(reference) if reference is not None else None
        self._azimuth_override = initial_azimuth
        if self.reference is not None:
            self.epoch_times = np.array([r.t for r in self.reference])
        self.lever_arm = np.asarray(config.odometer_lever_arm, dtype=np.float64)
        self.hard_iron = np.asarray(config.mag_hard_iron, dtype=np.float64)
        self.reset()

    # ----------------------------------------------------------------- public API
    def reset(self) -> None:
        """Forget everything: back to waiting for the static alignment."""
        self._reorder = ReorderBuffer(self.cfg.reorder_window_s)
        self._imu_t = np.empty(0)
        self._imu_g = np.empty((0, 3))
        self._imu_a = np.empty((0, 3))
        self._odo = OdometerSamples(np.empty(0), np.empty(0), np.empty(0))
        self._mag = MagSamples(np.empty(0), np.empty((0, 3)))
        self._markers: list[Marker] = []
        self._horizon = -math.inf
        self.state: NavState | None = None
        self.kf: ErrorStateKF | None = None
        self._carry = Carry.zero()
        self._out: list[NavEstimate] = []
        self._counts: dict[str, int] = defaultdict(int)
        self._first_marker: Marker | None = self.survey[0] if self.survey else None
        self._markers_seen: list[Marker] = []
        self._anchored = self.cfg.heading_source != "markers" or self.reference is not None
        self.reanchor_rad = 0.0
        self.initial_azimuth: float | None = None
        self._epoch = 0
        self._v_jac = np.zeros(3)
        self._prev_speed = 0.0
        self._prev_vel_mean: Array | None = None
        self._mag_ref: tuple[float, float] | None = None
        self._odo_start: float | None = None
        self._odo_quantum = self.cfg.odometer_resolution
        self._odo_last: float | None = None
        self._odo_learnt_t = -math.inf
        self._s_epoch_start = 0.0
        self._static_epochs = 0
        self.recording = Recording() if self.record else None
        self.datum: Datum | None = (
            Datum(self._first_marker.lat, self._first_marker.lon, self._first_marker.alt)
            if self._first_marker
            else None
        )

    def push_imu(self, t: float, gyro: Sequence[float], accel: Sequence[float]) -> None:
        """One IMU sample: stamp s, mean rate rad/s and mean specific force m/s^2, imu_link."""
        g = np.asarray(gyro, dtype=np.float64).reshape(3)
        a = np.asarray(accel, dtype=np.float64).reshape(3)
        if not (math.isfinite(t) and np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
            self._counts["dropped_nan_imu"] += 1
            return
        self._push(t, "imu", (g, a))

    def push_odometer(self, t: float, distance: float, speed: float) -> None:
        """One odometer sample: cumulative distance m and speed m/s."""
        if not all(math.isfinite(x) for x in (t, distance, speed)):
            self._counts["dropped_nan_odometer"] += 1
            return
        self._push(t, "odometer", (float(distance), float(speed)))

    def push_mag(self, t: float, field_t: Sequence[float]) -> None:
        """One magnetometer sample, tesla, imu_link."""
        m = np.asarray(field_t, dtype=np.float64).reshape(3)
        if not (math.isfinite(t) and np.all(np.isfinite(m))):
            self._counts["dropped_nan_mag"] += 1
            return
        self._push(t, "mag", m)

    def push_marker(self, marker: Marker) -> None:
        """One marker passage."""
        vals = (marker.t, marker.lat, marker.lon, marker.alt, *marker.sigma_enu)
        if not all(math.isfinite(x) for x in vals):
            self._counts["dropped_nan_marker"] += 1
            return
        self._push(marker.t, "marker", marker)

    def poll(self) -> list[NavEstimate]:
        """Estimates produced since the last call, in time order."""
        out, self._out = self._out, []
        return out

    def finish(self) -> list[NavEstimate]:
        """End of data: release and process everything still buffered."""
        self._ingest_released(self._reorder.release(flush=True), math.inf)
        return self.poll()

    def run(self, log: SensorLog, *, final: bool = True) -> None:
        """Offline fast path: ingest a time-sorted log (or consecutive chunks of one; pass
        final=False for all but the last chunk). Identical results to pushing the samples."""
        imu = log.imu
        ok = (
            np.isfinite(imu.t)
            & np.all(np.isfinite(imu.gyro), 1)
            & np.all(np.isfinite(imu.accel), 1)
        )
        self._counts["dropped_nan_imu"] += int((~ok).sum())
        horizon = math.inf if final else _last_stamp(log)
        self._ingest(
            imu.t[ok],
            imu.gyro[ok],
            imu.accel[ok],
            log.odometer,
            log.mag,
            list(log.markers),
            horizon,
        )

    def diagnostics(self) -> dict[str, int | float | str]:
        """Counters: samples per topic, dropped and late samples, accepted/rejected updates."""
        d: dict[str, int | float | str] = dict(self._counts)
        for kind, n in self._reorder.late.items():
            d[f"late_{kind}"] = n
        if self.kf is not None:
            d.update(self.kf.stats.as_dict())
        d["state"] = "navigating" if self.state is not None else "aligning"
        if self.state is not None:
            d["odometer_scale"] = 1.0 + self.state.k
            d["time"] = self.state.t
        return d

    # ----------------------------------------------------------------- ingestion
    def _push(self, t: float, kind: str, payload: object) -> None:
        self._counts[f"received_{kind}"] += 1
        self._reorder.push(t, kind, payload)
        if kind == "imu" and self._counts["received_imu"] % 8 and len(self._reorder) < 4096:
            return  # release in small batches; behaviour does not depend on batching
        released = self._reorder.release()
        if released:
            self._ingest_released(released, self._reorder.horizon)

    def _ingest_released(self, items: list[tuple[float, str, object]], horizon: float) -> None:
        imu_t, imu_g, imu_a, odo, mag, mk = [], [], [], [], [], []
        for t, kind, p in items:
            if kind == "imu":
                imu_t.append(t)
                imu_g.append(p[0])  # type: ignore[index]
                imu_a.append(p[1])  # type: ignore[index]
            elif kind == "odometer":
                odo.append((t, *p))  # type: ignore[misc]
            elif kind == "mag":
                mag.append((t, p))
            else:
                mk.append(p)
        o = np.array(odo).reshape(-1, 3)
        self._ingest(
            np.array(imu_t),
            np.array(imu_g).reshape(-1, 3),
            np.array(imu_a).reshape(-1, 3),
            OdometerSamples(o[:, 0], o[:, 1], o[:, 2]),
            MagSamples(np.array([m[0] for m in mag]), np.array([m[1] for m in mag]).reshape(-1, 3)),
            mk,  # type: ignore[arg-type]
            horizon,
        )

    def _ingest(
        self,
        imu_t: Array,
        gyro: Array,
        accel: Array,
        odo: OdometerSamples,
        mag: MagSamples,
        markers: list[Marker],
        horizon: float,
    ) -> None:
        r = self.r_base_imu
        if len(imu_t):
            self._imu_t = np.concatenate([self._imu_t, imu_t])
            self._imu_g = np.concatenate([self._imu_g, gyro @ r.T])
            self._imu_a = np.concatenate([self._imu_a, accel @ r.T])
        if len(odo):
            self._odo = OdometerSamples(
                np.concatenate([self._odo.t, odo.t]),
                np.concatenate([self._odo.distance, odo.distance]),
                np.concatenate([self._odo.speed, odo.speed]),
            )
            if self._odo_start is None:
                self._odo_start = float(odo.distance[0])
        if len(mag):
            self._mag = MagSamples(
                np.concatenate([self._mag.t, mag.t]),
                np.concatenate([self._mag.field, (mag.field - self.hard_iron) @ r.T]),
            )
        for m in markers:
            self._markers.append(m)
            self._markers_seen.append(m)
            if self._first_marker is None:
                self._first_marker = m
                if self.datum is None:
                    self.datum = Datum(m.lat, m.lon, m.alt)
        self._markers.sort(key=lambda m: m.t)
        self._horizon = horizon
        self._advance()

    @property
    def odometer_resolution(self) -> float:
        """Encoder resolution (m per count) in use: configured or learnt so far (0 = none)."""
        return self._odo_quantum

    def _odometer_resolution(self, t_now: float) -> float:
        """Encoder resolution used in the noise model (m), floored at 0.1 mm: configured, or
        the smallest nonzero step of the readings up to t_now (s) (the same whatever the
        batching of the input)."""
        if self.cfg.odometer_resolution <= 0.0:
            o = self._odo
            i0 = int(np.searchsorted(o.t, self._odo_learnt_t, side="right"))
            i1 = int(np.searchsorted(o.t, t_now, side="right"))
            if i1 > i0:
                dist = o.distance[i0:i1]
                prev = self._odo_last
                d = np.abs(np.diff(dist) if prev is None else _increments(prev, dist))
                self._odo_last = float(dist[-1])
                self._odo_learnt_t = float(o.t[i1 - 1])
                steps = d[d > 1e-9]
                if len(steps):
                    q = float(steps.min())
                    self._odo_quantum = q if self._odo_quantum <= 0.0 else min(self._odo_quantum, q)
        return max(self._odo_quantum, 1e-4)

    # ----------------------------------------------------------------- processing
    def _advance(self) -> None:
        while True:
            if self.state is None:
                if not self._try_align():
                    return
                continue
            end = self._next_epoch_end()
            if end is None:
                return
            self._process_epoch(end)

    def _odometer_at(self, t: Array) -> Array:
        """Odometer distance (m) interpolated at times t (sorted), from the buffered samples."""
        o = self._odo
        if len(o) == 0:
            return np.zeros_like(t)
        i0 = max(int(np.searchsorted(o.t, t[0])) - 1, 0)
        i1 = int(np.searchsorted(o.t, t[-1])) + 1
        return np.interp(t, o.t[i0:i1], o.distance[i0:i1])

    def _try_align(self) -> bool:
        t = self._imu_t
        if len(t) < 2:
            return False
        o = self._odo
        # End of the initial rest: first odometer move, or the first marker passage.
        moved = np.nonzero(np.abs(o.distance - o.distance[0]) > STATIC_MOVE_M)[0] if len(o) else []
        t_move = float(o.t[moved[0]]) if len(moved) else math.inf
        if self._first_marker is not None and self._first_marker.t > t[0]:
            t_move = min(t_move, self._first_marker.t)
        static_end = min(t_move, t[0] + max(self.cfg.static_alignment_s, 0.1) + 1e-9)
        enough = t[-1] >= static_end and self._horizon >= static_end
        if not enough:
            return False
        if self._first_marker is None and self._horizon < t_move + ALIGN_WAIT_S:
            return False  # wait for the launch marker to give the start position
        sel = t <= static_end
        if sel.sum() < 2:
            sel[:2] = True
        idx = np.nonzero(sel)[0]
        self._align(idx)
        return True

    def _align(self, idx: Array) -> None:
        cfg, lay = self.cfg, self.layout
        t = self._imu_t
        dts = np.diff(t[idx])
        w = np.r_[dts[0], dts]
        f_mean = np.average(self._imu_a[idx], axis=0, weights=w)
        g_mean = np.average(self._imu_g[idx], axis=0, weights=w)
        t_static = float(w.sum())
        roll, pitch = alignment.level(f_mean)
        first = self._first_marker
        lat, lon, h = (first.lat, first.lon, first.alt) if first else (0.0, 0.0, 0.0)
        azimuth, az_sigma = cfg.initial_azimuth, cfg.initial_heading_sigma
        if cfg.heading_source == "markers" and len(self.survey) >= 2:
            azimuth, _ = alignment.marker_bearing(self.survey[0], self.survey[1])
            if self.earth_sign < 0:  # reversed time: the pig backs along the bearing
                azimuth = float(np.mod(azimuth + np.pi, 2 * np.pi))
        mag_sel = self._mag.t <= t[idx[-1]]
        if mag_sel.any():
            m_mean = self._mag.field[mag_sel].mean(axis=0)
            self._mag_ref = (float(np.linalg.norm(m_mean)), 0.0)
            if cfg.heading_source == "magnetometer":
                azimuth = alignment.mag_azimuth(m_mean, roll, pitch, cfg.mag_declination)
                az_sigma = cfg.mag_heading_sigma
        if self.initial is not None:
            roll, pitch, azimuth = (float(x) for x in att.euler_from_dcm(self.initial.c_nb))
        if self._azimuth_override is not None:
            azimuth = float(self._azimuth_override)
        c = att.dcm_from_euler(roll, pitch, azimuth)
        if self._mag_ref is not None:
            m_n = c @ self._mag.field[mag_sel].mean(axis=0)
            self._mag_ref = (self._mag_ref[0], float(np.arctan2(-m_n[2], np.hypot(m_n[0], m_n[1]))))
        bg = alignment.gyro_bias_at_rest(g_mean, c, lat, self.earth_sign)
        s = NavState(
            t=float(t[idx[-1]]),
            lat=lat,
            lon=lon,
            h=h,
            vel_n=np.zeros(3),
            q_nb=att.quat_from_dcm(c),
            bg=bg,
            ba=np.zeros(3),
        )
        if self.initial is not None:
            s.bg, s.ba = self.initial.bg.copy(), self.initial.ba.copy()
            s.k, s.bore = self.initial.k, self.initial.bore.copy()
            s.gm = self.initial.gm.copy()
            s.am = self.initial.am.copy()
        s.distance = 0.0
        self.initial_azimuth = float(azimuth)
        P0 = self._initial_covariance(s, t_static, az_sigma)
        lin = s
        if self.reference is not None:
            # the prior stays the alignment's; only the linearization point moves
            lin = self.reference[0].copy()
            if abs(lin.t - s.t) > 1e-6:
                raise ValueError("the reference trajectory does not start at the alignment epoch")
            lin.distance = 0.0
            self.kf = ErrorStateKF(P0, cfg.gate_probability, s.difference(lin, lay))
            s = lin.inject(self.kf.x, lay)
        else:
            self.kf = ErrorStateKF(P0, cfg.gate_probability)
        self.state = s
        self._carry = Carry.zero()
        self._s_epoch_start = float(self._odometer_at(np.array([s.t]))[0])
        self._counts["aligned_at_ms"] = int(round(s.t * 1000))
        if self.recording is not None:
            zero = np.zeros(lay.n)
            self._record_epoch(
                None, None, zero, None, [], lin=lin, x_upd=self.kf.x, end_offset=zero
            )
        self._drop_processed()
        self._emit()

    def _initial_covariance(self, s: NavState, t_static: float, az_sigma: float) -> Array:
        """P0 with the couplings static alignment creates: levelled tilt absorbs the horizontal
        accelerometer error at rest (bias, and scale factor and misalignment times gravity),
        and the gyro bias absorbs the Earth rate error of the heading."""
        cfg, lay, imu = self.cfg, self.layout, self.imu_spec
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
        if self.initial is not None or t_static < 0.5:
            P[lay.bg, lay.bg] = np.eye(3) * bg_var
        else:
            G = -c.T @ att.skew(self.earth_sign * earth.earth_rate_n(s.lat))
            if not self._anchored:
                G[:, 2] = 0.0  # see _process_epoch: no gyrocompassing before the anchoring
            noise = imu.gyro_arw**2 / t_static + imu.gyro_bias_instability**2
            P[lay.bg, lay.bg] = G @ P_att @ G.T + np.eye(3) * noise
            P[lay.bg, lay.att] = G @ P_att
            P[lay.att, lay.bg] = P[lay.bg, lay.att].T
            P[lay.bg, src] = G @ P[lay.att, src]
            P[src, lay.bg] = P[lay.bg, src].T
        if lay.vel is not None:
            P[lay.vel, lay.vel] = np.eye(3) * cfg.zupt_sigma**2
        sig = self._first_marker.sigma_enu if self._first_marker else (1e3, 1e3, 1e3)
        P[lay.pos, lay.pos] = np.diag(np.maximum(np.square(sig), cfg.initial_position_sigma**2))
        P[lay.k, lay.k] = cfg.odometer_scale_sigma**2
        P[lay.bore, lay.bore] = np.eye(2) * cfg.boresight_sigma**2
        if lay.odoq is not None:
            P[lay.odoq, lay.odoq] = np.eye(2) * self._odometer_resolution(s.t) ** 2 / 12.0
        if lay.gm is not None:
            gm_var = np.full((3, 3), imu.gyro_misalignment**2)
            np.fill_diagonal(gm_var, imu.gyro_scale_factor**2)
            P[lay.gm, lay.gm] = np.diag(np.maximum(gm_var.reshape(9), 1e-12))
        return P

    def _next_epoch_end(self) -> int | None:
        s = self.state
        assert s is not None
        t = self._imu_t
        if len(t) == 0:
            return None
        if self.epoch_times is not None:
            i = int(np.searchsorted(self.epoch_times, s.t + 1e-9, side="right"))
            target = self.epoch_times[i] - 1e-9 if i < len(self.epoch_times) else math.inf
            end = int(np.searchsorted(t, target))
        else:
            target = s.t + 1.0 / self.cfg.filter_rate_hz - 1e-9
            end = int(np.searchsorted(t, target))
            pending = [m for m in self._markers if m.t > s.t]
            if pending:
                end = min(end, int(np.searchsorted(t, pending[0].t)))
        if end >= len(t):
            return None
        t_end = t[end]
        if self._horizon < t_end:
            return None
        o = self._odo
        covered = len(o) and o.t[-1] >= t_end
        if not covered and self._horizon < t_end + ODOMETER_TIMEOUT_S:
            return None
        return end

    def _process_epoch(self, end: int) -> None:
        cfg, lay = self.cfg, self.layout
        kf = self.kf
        assert self.state is not None and kf is not None
        ref = self.reference
        k_ep = self._epoch + 1
        if ref is not None and k_ep >= len(ref):
            raise ValueError("the data run past the end of the reference trajectory")
        # linearization point at the block start: the reference, or the filter's own estimate
        s0 = ref[k_ep - 1] if ref is not None else self.state
        t = self._imu_t[: end + 1]
        g = self._imu_g[: end + 1]
        a = self._imu_a[: end + 1]
        o = self._odo
        has_odo = bool(len(o)) and o.t[-1] >= t[-1] and o.t[0] <= s0.t + ODOMETER_TIMEOUT_S
        if not has_odo:
            self._counts["epochs_without_odometer"] += 1
        s_odo = self._odometer_at(t) if has_odo else np.full(len(t), self._s_epoch_start)
        ds = _increments(self._s_epoch_start, s_odo)
        if lay.has_vel:
            s1, blk, carry = ins_block(s0, t, g, a, self._carry, self.earth_sign)
        else:
            s1, blk, carry = dr_block(s0, t, g, a, ds, self._carry, self.lever_arm, self.earth_sign)
        T = blk.T
        speed = float(ds.sum() / T)
        w_yz = float(np.hypot(blk.omega_b[1], blk.omega_b[2]))
        lever_known = bool(np.any(self.lever_arm))
        bend_sigma = 0.0 if lever_known else 0.5 * cfg.pipe_diameter * w_yz * T
        w_dt = _increments(s0.t, t)
        gyro_mean = (g * w_dt[:, None]).sum(axis=0) / w_dt.sum()  # time-weighted, rad/s
        stopped = (
            has_odo
            and abs(speed) < cfg.stop_speed_threshold
            and abs(self._prev_speed) < cfg.stop_speed_threshold
            and float(np.linalg.norm(gyro_mean - s1.bg)) < cfg.stop_gyro_threshold
        )
        # the linearization point at the block end, and the velocity at which the Jacobians
        # that couple attitude and velocity are evaluated (first estimate; zero when stopped)
        s_lin = ref[k_ep] if ref is not None else s1
        v_jac = np.zeros(3) if stopped else s_lin.vel_n.copy()
        dv_f = None
        if lay.has_vel:
            # specific-force increment consistent with the Jacobian velocities at both ends:
            # dv_f + (v_jac(end) - v_nominal(end)) - (v_jac(start) - v_nominal(start))
            dv_f = blk.dv_f + (v_jac - s1.vel_n) - (self._v_jac - s0.vel_n)
        # Before the second marker anchors a heading taken from the markers, that heading can
        # be tens of degrees off: the Earth rate's dependence on it (gyrocompassing, real but
        # weak with a MEMS gyro) is then linearized too far from the truth and turns the
        # heading during the leg, so that the re-anchoring rotation no longer fits the path.
        # Until then the heading is left to the gyros alone.
        free = not self._anchored
        A = integrated_system_matrix(
            s0, blk, lay, self.earth_sign, at_rest=stopped, dv_f=dv_f, heading_free=free
        )
        Q = continuous_noise(
            s0,
            blk,
            lay,
            self.imu_spec,
            scale_rw=cfg.odometer_scale_rw,
            dr_along_sigma=cfg.odometer_distance_sigma,
            dr_lateral_sigma=cfg.dr_lateral_sigma,
            bend_sigma=bend_sigma,
            odometer_resolution=self._odometer_resolution(float(t[-1])),
        )
        phi, qd = discretize(A, Q, lay)
        offset = s1.difference(s_lin, lay) if ref is not None else None
        kf.predict(phi, qd, offset)
        s1.distance = s0.distance + (1.0 + s0.k) * float(ds.sum())
        s_pred = s1.copy()
        s = s_lin.copy() if ref is not None else s1
        due = [m for m in self._markers if m.t <= t[-1]]
        for m in due:
            self._markers.remove(m)
        due = [m for m in due if not self._late_marker(m, s)]
        for m in due:
            s, rz = self._before_marker(m, s)
            v_jac = rz @ v_jac  # the first-estimate velocity turns with the re-anchored state
        x_pred = kf.x.copy()
        P_pred = kf.P.copy() if self.recording is not None else None

        # Every update of the epoch is linearized at s (the prediction, or the reference); the
        # filter's mean error carries the corrections from one to the next (kalman.py), and
        # the ordinary EKF injects them into its nominal once, at the end of the epoch.
        def apply(m: meas.Measurement | None) -> None:
            if m is not None:
                kf.update(m)

        if lay.has_vel and has_odo:
            w, d = blk.omega_b, self.lever_arm
            lever_rate = float(w[1] * d[2] - w[2] * d[1])  # (omega x d)_x
            sigma_speed = math.hypot(
                cfg.over_epoch(cfg.odometer_speed_sigma, T),
                0.5 * cfg.pipe_diameter * w_yz * (not lever_known),
            )
            odo = meas.odometer_velocity(
                s,
                lay,
                speed=speed,
                vel_b_offset=blk.mean_vel_b - s1.c_nb.T @ s1.vel_n,
                lever_rate=lever_rate,
                sigma_speed=sigma_speed,
                sigma_nhc=cfg.over_epoch(cfg.nhc_sigma, T),
                vel_jac=v_jac,
                epoch_s=T,
            )
            apply(odo.rows([1, 2], "nhc"))
            if self._odometer_excluded(s0.t, t[-1]):
                self._counts["odometer_excluded"] += 1
            else:
                apply(odo.rows([0], "odometer"))
        if stopped:
            if lay.has_vel:
                apply(meas.zero_velocity(s, lay, cfg.zupt_sigma))
            zaru_sigma = math.sqrt(self.imu_spec.gyro_arw**2 / T + cfg.zaru_sigma**2)
            zaru = meas.zero_rate(
                s, lay, gyro_mean=gyro_mean, sigma=zaru_sigma, earth_sign=self.earth_sign
            )
            if free:
                zaru.H[:, lay.att.start + 2] = 0.0
            apply(zaru)
        if cfg.tilt_enabled() and has_odo:
            self._tilt_update(s, blk, T, apply)
        if cfg.mag_update:
            self._mag_update(s, blk, apply)
        for m in due:
            mm = meas.marker_fix(s, lay, m, time_sigma=cfg.marker_time_sigma)
            if self.recording is not None:
                self.recording.marker_residuals[m.name] = mm.residual.copy()
            apply(mm)

        if ref is not None:
            est = s_lin.inject(kf.x, lay)
            est.distance = s_lin.distance
            dx_rec = kf.x - x_pred
            end_offset = s_lin.difference(s1, lay)
        else:
            est = s.inject(kf.x, lay)
            kf.reset_mean()
            dx_rec = est.difference(s_pred, lay)
            end_offset = dx_rec
        self._prev_speed = speed
        self._prev_vel_mean = blk.dp / T
        self._v_jac = v_jac
        self._epoch = k_ep
        self.state = est
        self._carry = carry
        self._s_epoch_start = float(s_odo[-1])
        if self.recording is not None:
            self._record_epoch(
                P_pred, phi, dx_rec, blk, s_odo, lin=s_lin, x_upd=kf.x, end_offset=end_offset
            )
        self._counts["epochs"] += 1
        self._drop_processed(end)
        self._emit(status="static" if stopped else "moving", omega=blk.omega_b)

    def _odometer_excluded(self, t0: float, t1: float) -> bool:
        ex = self.odometer_exclude
        return bool(len(ex)) and bool(np.any((ex[:, 0] < t1) & (ex[:, 1] > t0)))

    def _tilt_update(self, s: NavState, blk: BlockResult, T: float, apply) -> None:  # noqa: ANN001
        cfg = self.cfg
        vel_mean = blk.dp / T
        if self._prev_vel_mean is None:
            return
        accel_n = (vel_mean - self._prev_vel_mean) / T
        g = earth.gravity(s.lat, s.h)
        f_norm = float(np.linalg.norm(blk.f_mean_n))
        if abs(f_norm - g) > cfg.tilt_gate or float(np.linalg.norm(accel_n)) > cfg.tilt_gate:
            self._counts["tilt_gated_motion"] += 1
            return
        apply(
            meas.gravity_tilt(
                s,
                self.layout,
                f_mean_n=blk.f_mean_n,
                c_mean=blk.sum_c_dt / T,
                accel_n=accel_n,
                sigma=cfg.tilt_sigma,
                c_f_mean=blk.sum_c_f_dt / T,
            )
        )

    def _mag_update(self, s: NavState, blk: BlockResult, apply) -> None:  # noqa: ANN001
        cfg = self.cfg
        i = int(np.searchsorted(self._mag.t, blk.t[-1], side="right")) - 1
        if i < 0 or self._mag.t[i] <= blk.t[-1] - blk.T + 1e-9 or self._mag_ref is None:
            return
        m_b = self._mag.field[i]
        j = min(int(np.searchsorted(blk.t, self._mag.t[i])), len(blk.t) - 1)
        # attitude at the sample, moved by the corrections applied since the block end
        c_sample = att.dcm_from_quat(blk.q_nb[j])
        ref_mag, ref_dip = self._mag_ref
        mag_norm = float(np.linalg.norm(m_b))
        m_n = c_sample @ m_b
        dip = float(np.arctan2(-m_n[2], np.hypot(m_n[0], m_n[1])))
        if (
            abs(mag_norm / ref_mag - 1.0) > cfg.mag_magnitude_gate
            or abs(dip - ref_dip) > cfg.mag_dip_gate
        ):
            self._counts["mag_disturbed"] += 1
            return
        apply(
            meas.magnetic_heading(
                s,
                self.layout,
                field_b=m_b,
                c_nb=c_sample,
                declination=cfg.mag_declination,
                sigma=cfg.mag_heading_sigma,
            )
        )

    def _late_marker(self, m: Marker, s: NavState) -> bool:
        if m.t < s.t - 2.0:
            self._counts["late_marker_dropped"] += 1
            return True
        return False

    def _before_marker(self, m: Marker, s: NavState) -> tuple[NavState, Array]:
        """What a marker passage does before the epoch's updates: the heading re-anchoring at
        the second marker (heading from the markers), and the recovery of a filter that has
        lost itself. A surveyed marker is the ground truth of this problem; when it disagrees
        with the prediction beyond the gate, the filter, not the marker, is wrong (accepted
        slips, a poor linearization): the predicted covariance is inflated until the marker is
        consistent (treated as extra process noise of this epoch, so that the smoother's
        record stays coherent) instead of rejecting the marker and diverging for good.
        Returns the state and the rotation applied to it (3, 3) (identity without
        re-anchoring)."""
        kf, lay = self.kf, self.layout
        assert kf is not None
        rz = np.eye(3)
        first = self._first_marker
        if not self._anchored and first is not None and m.name != first.name:
            s, d_az = alignment.reanchor_heading(s, first, m)
            # the error state rotates with the nominal: nav-frame blocks of P turn with it
            rot = np.eye(lay.n)
            rz = att.dcm_from_rotvec(np.array([0.0, 0.0, -d_az]))
            for sl in (lay.att, lay.vel, lay.pos):
                if sl is not None:
                    rot[sl, sl] = rz
            kf.P = rot @ kf.P @ rot.T
            kf.x = rot @ kf.x
            self._anchored = True
            self.reanchor_rad = d_az
            self._counts["heading_reanchor_mdeg"] = int(round(math.degrees(d_az) * 1000))
        mm = meas.marker_fix(s, lay, m, time_sigma=self.cfg.marker_time_sigma)
        r = mm.residual - mm.H @ kf.x
        S = mm.H @ kf.P @ mm.H.T + mm.R
        nis = float(r @ np.linalg.solve(S, r))
        limit = chi2_threshold(self.cfg.gate_probability, len(r))
        if np.isfinite(nis) and nis > limit:
            kf.P = kf.P * (nis / len(r))
            self._counts["marker_covariance_inflations"] += 1
        return s, rz

    # ----------------------------------------------------------------- bookkeeping
    def _drop_processed(self, end: int | None = None) -> None:
        s = self.state
        assert s is not None
        i = int(np.searchsorted(self._imu_t, s.t, side="right"))
        # slices are views: O(1) per epoch whatever the length of the log
        self._imu_t, self._imu_g, self._imu_a = self._imu_t[i:], self._imu_g[i:], self._imu_a[i:]
        o = self._odo
        i = max(int(np.searchsorted(o.t, s.t)) - 1, 0)
        if i > 0:
            self._odo = o.slice(slice(i, None))
        mg = self._mag
        i = int(np.searchsorted(mg.t, s.t - 1.0, side="right"))
        if i > 0:
            self._mag = mg.slice(slice(i, None))

    def _emit(self, status: str = "static", omega: Array | None = None) -> None:
        s, kf, lay = self.state, self.kf, self.layout
        assert s is not None and kf is not None
        cov_pose = kf.P[self._pose_ix]
        cov_vel = (
            kf.P[lay.vel, lay.vel].copy()
            if lay.vel is not None
            else np.eye(3) * self.cfg.odometer_speed_sigma**2
        )
        self._out.append(
            NavEstimate(
                t=s.t,
                lat=s.lat,
                lon=s.lon,
                h=s.h,
                vel_n=s.vel_n.copy(),
                quat_nb=s.q_nb.copy(),
                omega_b=np.zeros(3) if omega is None else omega.copy(),
                cov_pose=cov_pose,
                cov_vel_n=cov_vel,
                distance=s.distance,
                status=status,
            )
        )

    def _record_epoch(
        self,
        P_pred: Array | None,
        phi: Array | None,
        dx: Array,
        blk: BlockResult | None,
        s_odo: Array | list,
        *,
        lin: NavState,
        x_upd: Array,
        end_offset: Array,
    ) -> None:
        rec = self.recording
        assert rec is not None and self.state is not None and self.kf is not None
        n = self.layout.n
        rec.t.append(self.state.t)
        rec.states.append(self.state.copy())
        rec.lin.append(lin.copy() if self.reference is not None else rec.states[-1])
        rec.x_upd.append(x_upd.copy())
        rec.P_upd.append(self.kf.P.copy())
        rec.P_pred.append(self.kf.P.copy() if P_pred is None else P_pred)
        rec.phi.append(np.eye(n) if phi is None else phi)
        rec.dx.append(dx)
        rec.end_offset.append(end_offset)
        k = len(rec.t) - 1
        if blk is not None:
            rec.s_t.append(blk.t.copy())
            rec.s_odo.append(np.asarray(s_odo, dtype=np.float64).copy())
            rec.s_lat.append(blk.lat.copy())
            rec.s_lon.append(blk.lon.copy())
            rec.s_h.append(blk.h.copy())
            rec.s_q.append(blk.q_nb.copy())
            rec.s_epoch.append(np.full(len(blk.t), k))


def _increments(x0: float, x: Array) -> Array:
    """x[i] - x[i - 1] for every i, with x[-1] = x0 (np.diff with prepend, without its
    overhead on the short per-epoch arrays)."""
    before = np.empty_like(x)
    before[0] = x0
    before[1:] = x[:-1]
    return x - before


def _last_stamp(log: SensorLog) -> float:
    ends = [x.t[-1] for x in (log.imu, log.odometer, log.mag) if len(x)]
    return max(ends) if ends else -math.inf


def apply_mount(log: SensorLog, config: NavConfig) -> SensorLog:
    """The log with imu_link vectors rotated into base_link per config.imu_mount_rpy."""
    return log.to_base_link(mount_rotation(config.imu_mount_rpy))


__all__ = ["NavEstimate", "Navigator", "Recording", "ImuSamples"]
