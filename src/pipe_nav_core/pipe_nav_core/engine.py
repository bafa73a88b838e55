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
The epochs run compiled (:mod:`pipe_nav_core.epoch`), as many per call as the buffered data
allow (one at a time live, thousands offline: the results do not depend on it); this class
plans them, prepares their inputs, handles alignment and marker passages, and keeps the
results.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from . import alignment, earth, imu_model
from . import attitude as att
from . import measurements as meas
from .config import AUTO_GRADE, NavConfig
from .epoch import (
    COUNTERS,
    D_FREE,
    D_S_START,
    D_SIZE,
    KINDS,
    S_LIN,
    W_VJAC,
    Batch,
    Filter,
    Inputs,
    parameters,
    run_epochs,
)
from .jit import kernel
from .kalman import ErrorStateKF, chi2_threshold
from .measurements import marker_vector
from .recording import Recording
from .sensors import ImuSpec
from .state import (
    SV_DIST,
    SV_H,
    SV_LAT,
    SV_LON,
    SV_Q,
    SV_SIZE,
    SV_T,
    SV_VEL,
    Layout,
    NavState,
    layout_for,
)
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
MAX_BATCH = 1024  # epochs per call of the compiled epoch loop (bounds its output buffers)
ALIGN_WAIT_S = 5.0  # after motion starts, wait this long for the first marker before starting
STATIC_MOVE_M = 0.005  # odometer change that ends the initial rest
# rad: the live filter's own heading prior while its heading is unanchored; the rest of the
# configured prior is carried outside the filter as a rotation about the first marker (FreeHeading)
FREE_HEADING_SIGMA = math.radians(0.1)

# rad^2: the variance of an azimuth uniform over the circle
UNKNOWN_HEADING_VARIANCE = math.pi**2 / 3.0


def _uniform_rotation_cov(d: Array) -> Array:
    """(..., 2, 2) second moments of (R(a) - I) d for horizontal vectors d (..., 2) and a
    uniform angle a: 1.5 d d^T + 0.5 d_perp d_perp^T (the error of a vector turned by an
    unknown heading)."""
    d = np.asarray(d, dtype=np.float64)
    perp = np.stack([-d[..., 1], d[..., 0]], axis=-1)
    return 1.5 * d[..., :, None] * d[..., None, :] + 0.5 * perp[..., :, None] * perp[..., None, :]


@dataclass(frozen=True)
class FreeHeading:
    """The part of the initial heading uncertainty that the live filter keeps outside its
    covariance until the heading is anchored at the second marker.

    Before the anchoring nothing the filter measures sees the heading (odometer, NHC, zero
    velocity and rate, tilt; the Earth rate's heading coupling is left out, epoch.py): an
    error of the initial heading rotates the whole solution about the vertical through the
    first marker and is never observed. Inside an EKF a prior of tens of degrees on such a
    direction is harmful: the gains computed from it are wrong at second order, and the
    heading wanders by tens of degrees on the way (27 degrees over 100 m on sag104). So the
    filter runs with FREE_HEADING_SIGMA, and the rest, a rotation angle of this variance, is
    added to what is reported (the Navigator's estimates, :meth:`variances`) and folded into
    the filter at the second marker before its fix. Linearly this equals carrying it inside.

    variance rad^2; lat, lon rad, h m: the pivot (first marker); until: s, the time of the
    anchoring (inf while unanchored); unknown: the heading is not known at all (markers as
    the heading source but fewer than two surveyed: the azimuth is the configured default),
    variance is then that of a uniform azimuth, UNKNOWN_HEADING_VARIANCE, and the reported
    covariances are those of a solution rotated by a uniform angle, not its linearization.
    """

    variance: float
    lat: float
    lon: float
    h: float
    until: float = math.inf
    unknown: bool = False

    def direction(self, lat: Array, lon: Array, h: Array, vel_n: Array, layout: Layout) -> Array:
        """(N, n) error-state direction (layout) of a unit rotation (rad) of the solution about
        the vertical through the pivot, at positions lat, lon rad, h m and velocities (N, 3)
        m/s ENU: attitude (0, 0, 1), velocity up x v, position up x (p - pivot)."""
        d = self._offset(lat, lon, h)
        v = np.asarray(vel_n, dtype=np.float64).reshape(-1, 3)
        g = np.zeros((len(d), layout.n))
        g[:, layout.att.start + 2] = 1.0
        if layout.vel is not None:
            g[:, layout.vel.start], g[:, layout.vel.start + 1] = -v[:, 1], v[:, 0]
        g[:, layout.pos.start], g[:, layout.pos.start + 1] = -d[:, 1], d[:, 0]
        return g

    def covariance(self, lat: float, lon: float, h: float, vel_n: Array, layout: Layout) -> Array:
        """(n, n) covariance (layout) this uncertainty adds to the estimate at lat, lon rad,
        h m with velocity vel_n m/s ENU."""
        if not self.unknown:
            g = self.direction(lat, lon, h, vel_n, layout)[0]
            return self.variance * np.outer(g, g)
        out = np.zeros((layout.n, layout.n))
        a = layout.att.start + 2
        out[a, a] = self.variance
        p = layout.pos.start
        out[p : p + 2, p : p + 2] = _uniform_rotation_cov(self._offset(lat, lon, h)[0, :2])
        if layout.vel is not None:
            v = layout.vel.start
            out[v : v + 2, v : v + 2] = _uniform_rotation_cov(np.asarray(vel_n)[:2])
        return out

    def variances(self, t: Array, lat: Array, lon: Array, h: Array) -> Array:
        """(N, 3) variances added to east, north (m^2) and azimuth (rad^2) at times t (s)."""
        d = self._offset(lat, lon, h)
        on = np.asarray(t, dtype=np.float64).reshape(-1) < self.until
        if self.unknown:
            c = _uniform_rotation_cov(d[:, :2])
            out = np.stack([c[:, 0, 0], c[:, 1, 1], np.full(len(d), self.variance)], axis=-1)
        else:
            out = self.variance * np.stack([d[:, 1] ** 2, d[:, 0] ** 2, np.ones(len(d))], axis=-1)
        return np.where(on[:, None], out, 0.0)

    def _offset(self, lat: Array, lon: Array, h: Array) -> Array:
        """(N, 3) ENU offsets (m) of positions lat, lon rad, h m from the pivot."""
        return earth.geodetic_to_enu(lat, lon, h, self.lat, self.lon, self.h).reshape(-1, 3)


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


def mount_rotation(rpy: Sequence[float]) -> Array:
    """Rotation imu_link -> base_link from (roll, pitch, yaw) rad: Rz(yaw) Ry(pitch) Rx(roll)."""
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


# a gate that rejects more than this share of an update kind (out of at least MIN_UPDATES) is
# fighting a filter that trusts its model more than the data
REJECTED_SHARE, MIN_UPDATES = 0.1, 50
# an estimated gyro bias this many times the grade's turn-on bias means another grade of IMU
BIAS_FACTOR = 5.0


def model_warnings(
    diag: dict[str, int | float | str], gyro_bias: Array, spec: ImuSpec
) -> list[str]:
    """One line per sign that the IMU noise model does not fit the data: a gate that rejects
    many odometer or non-holonomic updates, or a gyro bias (rad/s, base_link) far beyond the
    grade's turn-on bias. Both show a filter more confident than its sensors, whose centreline
    and sigmas are not to be trusted."""
    out = []
    for kind in ("nhc", "odometer"):
        acc = int(diag.get(f"accepted_{kind}", 0))
        rej = int(diag.get(f"rejected_{kind}", 0))
        if acc + rej >= MIN_UPDATES and rej > REJECTED_SHARE * (acc + rej):
            out.append(
                f"{rej / (acc + rej):.0%} of the {kind} updates were rejected: the filter trusts "
                f"its IMU model ({spec.name}) more than the data; check imu_grade (--imu-grade)"
            )
    worst = float(np.max(np.abs(gyro_bias))) if len(gyro_bias) else 0.0
    if worst > BIAS_FACTOR * spec.gyro_turn_on_bias:
        out.append(
            f"estimated gyro bias {np.degrees(worst) * 3600:.0f} deg/h is "
            f"{worst / spec.gyro_turn_on_bias:.0f} times the {spec.name} grade's turn-on bias "
            f"({np.degrees(spec.gyro_turn_on_bias) * 3600:.0f} deg/h); "
            "check imu_grade (--imu-grade)"
        )
    return out


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
    Gauss-Newton step of the batch problem (iterated smoother, :mod:`pipe_nav_core.smooth.passes`);
    initial_azimuth: rad, replaces the initial heading of the configured source (the smoother
    iterates the re-anchoring at the second marker with it); free_heading: keep the initial
    heading's prior outside the filter until the next marker after the first (:class:`FreeHeading`);
    default: while the heading from the markers is unanchored (the live filter). Not for a
    pass the RTS smooths: to it the prior's return at that marker is process noise.

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
        emit: bool = True,
        reverse: bool = False,
        initial: NavState | None = None,
        epoch_times: Array | None = None,
        odometer_exclude: Array | None = None,
        reference: Sequence[NavState] | Array | None = None,
        initial_azimuth: float | None = None,
        free_heading: bool | None = None,
    ) -> None:
        config.validate()
        self.cfg = config
        self.layout = layout_for(config)
        pose = [*range(self.layout.pos.start, self.layout.pos.stop)]
        pose += range(self.layout.att.start, self.layout.att.stop)
        self._pose_ix = np.ix_(pose, pose)  # [position, attitude] rows/columns of P
        self.imu_spec = config.imu_spec()
        # imu_grade auto: the noise model is chosen from the initial rest at the alignment
        # (imu_model.choose_at_rest), or from these per-sample variances the Imu messages
        # declare ({"gyro_variance": 3 x (rad/s)^2, "accel_variance": 3 x (m/s^2)^2}), which
        # the caller may set before the data; imu_choice says what was chosen and why.
        self.declared_imu_noise: dict[str, list[float]] | None = None
        self.imu_choice: imu_model.ImuModelChoice | None = None
        self.r_base_imu = mount_rotation(config.imu_mount_rpy)
        self.earth_sign = -1.0 if reverse else 1.0
        self.survey = markers_sorted(survey)
        self.record = record
        self.emit = emit
        self.initial = initial
        ex = np.zeros((0, 2)) if odometer_exclude is None else np.asarray(odometer_exclude, float)
        self.odometer_exclude = ex[np.argsort(ex[:, 0], kind="stable")].reshape(-1, 2)
        self.epoch_times = None if epoch_times is None else np.sort(np.asarray(epoch_times, float))
        self.reference = _flat_states(reference)
        self._azimuth_override = initial_azimuth
        self._free_option = free_heading
        if self.reference is not None:
            self.epoch_times = self.reference[:, SV_T].copy()
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
        self._sv = np.zeros(SV_SIZE)  # the state as the compiled epoch keeps it
        self._carry = np.zeros(6)
        self._dyn = np.zeros(D_SIZE)
        self._prm: Array | None = None
        self._batches: list[Batch | None] = [None, None]
        self._batch_turn = 0
        self._out: list[NavEstimate] = []
        self._counts: dict[str, int] = defaultdict(int)
        self._first_marker: Marker | None = self.survey[0] if self.survey else None
        self._markers_seen: list[Marker] = []
        self._anchored = self.cfg.heading_source != "markers" or self.reference is not None
        self.reanchor_rad = 0.0
        self.initial_azimuth: float | None = None
        self.free_heading: FreeHeading | None = None
        self._epoch = 0
        self._mag_ref: tuple[float, float] | None = None
        self._odo_start: float | None = None
        self._odo_quantum = self.cfg.odometer_resolution
        self._odo_last: float | None = None
        self._odo_learnt_t = -math.inf
        self._static_epochs = 0
        self.recording = Recording(self.layout, reference=self.reference) if self.record else None
        self.datum: Datum | None = (
            Datum(self._first_marker.lat, self._first_marker.lon, self._first_marker.alt)
            if self._first_marker
            else None
        )

    def push_imu(self, t: float, gyro: Sequence[float], accel: Sequence[float]) -> None:
        """One IMU sample: stamp s, mean rate rad/s and mean specific force m/s^2, imu_link."""
        gx, gy, gz = (float(v) for v in gyro)  # scalars: numpy per sample costs more here
        ax, ay, az = (float(v) for v in accel)
        if not all(map(math.isfinite, (t, gx, gy, gz, ax, ay, az))):
            self._counts["dropped_nan_imu"] += 1
            return
        self._push(t, "imu", ((gx, gy, gz), (ax, ay, az)))

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
        if self.imu_choice is not None:
            d["imu_model"] = self.imu_choice.grade
            d["imu_model_reason"] = self.imu_choice.reason
        if self.state is not None:
            d["odometer_scale"] = 1.0 + self.state.k
            d["time"] = self.state.t
        return d

    @property
    def reorder_horizon(self) -> float:
        """Stamp (s) up to which samples have left the reorder window: a sample stamped at or
        before it would be late (dropped and counted)."""
        return float(self._reorder.horizon)

    def model_warnings(self) -> list[str]:
        """Signs that the IMU noise model does not fit the data so far (:func:`model_warnings`);
        empty when it fits."""
        bg = self.state.bg if self.state is not None else np.zeros(0)
        return model_warnings(self.diagnostics(), bg, self.imu_spec)

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
        return float(self._odometer_resolutions(np.array([t_now]))[0])

    def _odometer_resolutions(self, t_now: Array) -> Array:
        """_odometer_resolution at each of the increasing times t_now (s)."""
        if self.cfg.odometer_resolution > 0.0:
            return np.full(len(t_now), max(self.cfg.odometer_resolution, 1e-4))
        o = self._odo
        i0 = int(np.searchsorted(o.t, self._odo_learnt_t, side="right"))
        upto = np.searchsorted(o.t, t_now, side="right") - i0  # readings learnt from per time
        quantum = self._odo_quantum if self._odo_quantum > 0.0 else math.inf
        if upto[-1] <= 0:
            return np.full(len(t_now), max(self._odo_quantum, 1e-4))
        dist = o.distance[i0 : i0 + upto[-1]]
        prev = self._odo_last
        d = (
            np.abs(_increments(prev, dist))
            if prev is not None
            else np.abs(np.diff(dist, prepend=dist[0]))
        )
        smallest = np.minimum.accumulate(np.where(d > 1e-9, d, math.inf))
        learnt = np.r_[quantum, np.minimum(smallest, quantum)]  # [k]: after k readings
        out = learnt[np.maximum(upto, 0)]
        self._odo_last = float(dist[-1])
        self._odo_learnt_t = float(o.t[i0 + upto[-1] - 1])
        self._odo_quantum = float(learnt[-1]) if math.isfinite(learnt[-1]) else self._odo_quantum
        return np.maximum(np.where(np.isfinite(out), out, 0.0), 1e-4)

    # ----------------------------------------------------------------- processing
    def _advance(self) -> None:
        while True:
            if self.state is None:
                if not self._try_align():
                    return
                continue
            ends, marker_due = self._plan()
            if not len(ends):
                return
            if marker_due:
                if len(ends) > 1:
                    self._run_batch(ends[:-1])
                    ends = ends[-1:] - (ends[-2] + 1)  # the buffer now starts after ends[-2]
                self._run_marker_epoch(ends)
            else:
                self._run_batch(ends)

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
        if cfg.imu_grade == AUTO_GRADE:
            self.imu_choice = imu_model.choose_at_rest(
                t[idx], self._imu_g[idx], self._imu_a[idx], cfg, self.declared_imu_noise
            )
            self.imu_spec = self.imu_choice.config.imu_spec()
        dts = np.diff(t[idx])
        w = np.r_[dts[0], dts]
        f_mean = np.average(self._imu_a[idx], axis=0, weights=w)
        g_mean = np.average(self._imu_g[idx], axis=0, weights=w)
        t_static = float(w.sum())
        roll, pitch = alignment.level(f_mean)
        first = self._first_marker
        lat, lon, h = (first.lat, first.lon, first.alt) if first else (0.0, 0.0, 0.0)
        azimuth, az_sigma = cfg.initial_azimuth, cfg.initial_heading_sigma
        markers_source = cfg.heading_source == "markers"
        bearing = markers_source and len(self.survey) >= 2
        if bearing:
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
        free = not self._anchored if self._free_option is None else self._free_option
        # markers as the source but no bearing, and no azimuth given in its place
        unknown = (
            markers_source
            and not bearing
            and self.initial is None
            and self._azimuth_override is None
        )
        if free and not cfg.mag_update and (unknown or az_sigma > FREE_HEADING_SIGMA):
            var = UNKNOWN_HEADING_VARIANCE if unknown else az_sigma**2 - FREE_HEADING_SIGMA**2
            self.free_heading = FreeHeading(var, s.lat, s.lon, s.h, unknown=unknown)
            az_sigma = FREE_HEADING_SIGMA
        P0 = self._initial_covariance(s, t_static, az_sigma)
        lin = s
        if self.reference is not None:
            # the prior stays the alignment's; only the linearization point moves
            lin = NavState.from_vector(self.reference[0])
            if abs(lin.t - s.t) > 1e-6:
                raise ValueError("the reference trajectory does not start at the alignment epoch")
            lin.distance = 0.0
            self.kf = ErrorStateKF(P0, cfg.gate_probability, s.difference(lin, lay))
            s = lin.inject(self.kf.x, lay)
        else:
            self.kf = ErrorStateKF(P0, cfg.gate_probability)
        self.state = s
        self._sv = s.vector()
        self._carry = np.zeros(6)
        self._dyn = np.zeros(D_SIZE)
        self._dyn[D_S_START] = float(self._odometer_at(np.array([s.t]))[0])
        self._dyn[D_FREE] = not self._anchored
        self._prm = parameters(cfg, self.imu_spec, self.lever_arm, self.earth_sign, self._mag_ref)
        self._counts["aligned_at_ms"] = int(round(s.t * 1000))
        if self.recording is not None:
            self._record_alignment()
        self._drop_processed()
        if self.emit:
            self._out.append(self._estimate(self._sv, self.kf.P, np.zeros(3), "static"))

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
                G[:, 2] = 0.0  # no gyrocompassing before the anchoring (epoch.py, heading_free)
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

    def _plan(self) -> tuple[NDArray[np.int64], bool]:
        """The next epochs' last IMU samples (indices into the buffer), at most MAX_BATCH, and
        whether the last of them is a marker passage's epoch (then it is the only one with a
        marker due)."""
        s = self.state
        assert s is not None
        period = 1.0 / self.cfg.filter_rate_hz
        times = self.epoch_times if self.epoch_times is not None else np.empty(0)
        mk = np.array([m.t for m in self._markers]) if self._markers else np.empty(0)
        odo_end = float(self._odo.t[-1]) if len(self._odo) else -math.inf
        return _plan_epochs(
            self._imu_t,
            s.t,
            period,
            times,
            mk,
            self._horizon,
            odo_end,
            ODOMETER_TIMEOUT_S,
            MAX_BATCH,
        )

    def _inputs(self, ends: NDArray[np.int64]) -> Inputs:
        """The data of the epochs ending at these IMU samples: the samples, per epoch the
        odometer coverage, excluded (slip), encoder resolution and magnetometer sample, per IMU
        sample the odometer reading."""
        assert self.state is not None
        t = self._imu_t[: ends[-1] + 1]
        t_end = t[ends]
        t_start = np.r_[self.state.t, t_end[:-1]]
        o = self._odo
        s_odo = self._odometer_at(t)
        if len(o):
            # readings around the epoch, neither over ODOMETER_TIMEOUT_S away: across a longer
            # silence (a dropout, a stuck wheel's readings left out) the count interpolated
            # between its ends is not a measurement
            before = o.t[np.maximum(np.searchsorted(o.t, t_start, side="right") - 1, 0)]
            after = o.t[np.minimum(np.searchsorted(o.t, t_end, side="left"), len(o.t) - 1)]
            has_odo = ((o.t[-1] >= t_end) & (before <= t_start + 1e-9)
                       & (t_start - before <= ODOMETER_TIMEOUT_S)
                       & (after - t_end <= ODOMETER_TIMEOUT_S))  # fmt: skip
        else:
            has_odo = np.zeros(len(ends), dtype=bool)
        ex = self.odometer_exclude
        excluded = np.zeros(len(ends), dtype=bool)
        if len(ex):
            # some interval starts before the epoch's end and ends after its start
            lo = np.searchsorted(ex[:, 0], t_end)
            latest_end = np.maximum.accumulate(ex[:, 1])[np.maximum(lo - 1, 0)]
            excluded = (lo > 0) & (latest_end > t_start)
        mag_i = np.searchsorted(self._mag.t, t_end, side="right") - 1
        ok = mag_i >= 0
        ok[ok] = self._mag.t[mag_i[ok]] > t_start[ok] + 1e-9
        mag_i = np.where(ok, mag_i, -1)
        res = self._odometer_resolutions(t_end)
        n = ends[-1] + 1
        return Inputs(
            self._imu_t[:n], self._imu_g[:n], self._imu_a[:n], ends, s_odo, has_odo, excluded,
            res, mag_i, self._mag.t, self._mag.field,
        )  # fmt: skip

    def _call(
        self,
        batch: Batch,
        inputs: Inputs,
        markers: Array,
        *,
        stop: bool = False,
        resume: bool = False,
    ) -> None:
        kf = self.kf
        assert kf is not None and self._prm is not None
        ref = self.reference if self.reference is not None else np.empty((0, SV_SIZE))
        state = Filter(self._sv, kf.x, kf.P, self._carry, self._dyn)
        run_epochs(
            stop, resume, self._epoch + 1, state, self.layout.index, self._prm, ref, inputs,
            markers, batch.buffers(),
        )  # fmt: skip

    def _batch_for(self, epochs: int, samples: int) -> Batch:
        """The output buffers, reused from batch to batch (fresh memory costs page faults);
        two in turn when recording, the recording packing one's covariances in a second
        thread while the next batch runs (Recording.add_epochs)."""
        if self.recording is not None:
            self._batch_turn ^= 1
        b = self._batches[self._batch_turn]
        if b is None or len(b.sv) < epochs or len(b.lat) < samples:
            size = max(epochs, MAX_BATCH if self.recording is not None else 1)
            b = Batch(size, max(samples, 2 * size * 20), self.layout.n)
            self._batches[self._batch_turn] = b
        b.reset()
        return b

    def _run_batch(self, ends: NDArray[np.int64]) -> None:
        """Epochs without a marker passage, all in one call of the compiled loop."""
        batch = self._batch_for(len(ends), int(ends[-1]) + 1)
        self._call(batch, self._inputs(ends), np.zeros((0, 7)))
        self._finish(batch, ends)

    def _run_marker_epoch(self, ends: NDArray[np.int64]) -> None:
        """The epoch of a marker passage: prediction, then (Python) the heading re-anchoring
        and the covariance recovery of _before_marker, then the updates with the marker fix."""
        assert self.kf is not None and self.state is not None
        t_end = self._imu_t[ends[-1]]
        due = [m for m in self._markers if m.t <= t_end]
        for m in due:
            self._markers.remove(m)
        batch = Batch(1, int(ends[-1]) + 1, self.layout.n)
        inputs = self._inputs(ends)
        self._call(batch, inputs, np.zeros((0, 7)), stop=True)
        s = NavState.from_vector(batch.ws_sv[S_LIN])
        due = [m for m in due if not self._late_marker(m, s)]
        v_jac = batch.ws[W_VJAC : W_VJAC + 3]
        for m in due:
            s, rz = self._before_marker(m, s)
            v_jac[:] = rz @ v_jac  # the first-estimate velocity turns with the re-anchored state
        batch.ws_sv[S_LIN] = s.vector()
        batch.ws_x[:] = self.kf.x  # the prediction as _before_marker left it
        batch.P_pred[0] = self.kf.P
        mk = np.array([marker_vector(m) for m in due]).reshape(-1, 7)
        batch.marker_res = np.zeros((len(due), 3))
        self._call(batch, inputs, mk, resume=True)
        if self.recording is not None:
            for m, r in zip(due, batch.marker_res, strict=True):
                self.recording.marker_residuals[m.name] = r.copy()
        self._dyn[D_FREE] = not self._anchored
        self._finish(batch, ends)

    def _finish(self, batch: Batch, ends: NDArray[np.int64]) -> None:
        """Take a batch's results: state, counters, recording, estimates; drop its samples."""
        kf = self.kf
        assert kf is not None
        nb = len(ends)
        self.state = NavState.from_vector(self._sv)
        for name, c in zip(COUNTERS, batch.counts, strict=True):
            if c:
                self._counts[name] += int(c)
        st = kf.stats
        for k, name in enumerate(KINDS):
            if batch.acc[k] or batch.rej[k]:
                st.accepted[name] += int(batch.acc[k])
                st.rejected[name] += int(batch.rej[k])
                st.nis_sum[name] += float(batch.nis[k])
                st.dof_sum[name] += int(batch.dof[k])
        if self.recording is not None:
            self._record_batch(batch, ends)
        if self.emit:
            self._emit_batch(batch, nb)
        self._epoch += nb
        self._drop_processed()

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
        later = first is not None and m.name != first.name
        free = self.free_heading
        if later and free is not None and free.until == math.inf:
            # the heading prior back into the filter (before a re-anchoring rotation)
            g = free.direction(s.lat, s.lon, s.h, s.vel_n, lay)[0]
            kf.P += free.variance * np.outer(g, g)
            self.free_heading = replace(free, until=s.t)
        if not self._anchored and first is not None and later:
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
    def _drop_processed(self) -> None:
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

    def _estimate(self, v: Array, P: Array, omega: Array, status: str) -> NavEstimate:
        """The estimate of flat state v with covariance P (n, n) and body rate omega."""
        lay = self.layout
        free = self.free_heading
        if free is not None and v[SV_T] < free.until:  # the heading prior kept outside P
            P = P + free.covariance(v[SV_LAT], v[SV_LON], v[SV_H], v[SV_VEL], lay)
        cov_vel = (
            P[lay.vel, lay.vel].copy()
            if lay.vel is not None
            else np.eye(3) * self.cfg.odometer_speed_sigma**2
        )
        return NavEstimate(
            t=float(v[SV_T]),
            lat=float(v[SV_LAT]),
            lon=float(v[SV_LON]),
            h=float(v[SV_H]),
            vel_n=v[SV_VEL].copy(),
            quat_nb=v[SV_Q].copy(),
            omega_b=omega.copy(),
            cov_pose=P[self._pose_ix],
            cov_vel_n=cov_vel,
            distance=float(v[SV_DIST]),
            status=status,
        )

    def _emit_batch(self, batch: Batch, nb: int) -> None:
        for e in range(nb):
            status = "static" if batch.stopped[e] else "moving"
            self._out.append(self._estimate(batch.sv[e], batch.P_upd[e], batch.omega[e], status))

    def _record_batch(self, batch: Batch, ends: NDArray[np.int64]) -> None:
        rec = self.recording
        assert rec is not None
        nb = len(ends)
        linearized = self.reference is not None
        rec.add_epochs(
            batch.sv[:nb],
            dx=batch.dx[:nb],
            P_upd=batch.P_upd[:nb],
            P_pred=batch.P_pred[:nb],
            phi=batch.phi[:nb],
            x_upd=batch.x_upd[:nb] if linearized else None,
            end_offset=batch.end_offset[:nb] if linearized else None,
        )
        b = batch
        rec.add_blocks(ends, self._imu_t, b.s_odo, b.lat, b.lon, b.h, b.q)

    def _record_alignment(self) -> None:
        """Epoch 0 of the recording: the aligned state, its prior, no transition."""
        rec, kf = self.recording, self.kf
        assert rec is not None and kf is not None and self.state is not None
        n = self.layout.n
        zero = np.zeros(n)
        linearized = self.reference is not None
        rec.add_epoch(
            self._sv.copy(),
            dx=zero,
            P_upd=kf.P,
            P_pred=kf.P,
            phi=np.eye(n),
            x_upd=kf.x.copy() if linearized else None,
            end_offset=zero if linearized else None,
        )


@kernel
def _plan_epochs(
    t: Array,
    t0: float,
    period: float,
    epoch_times: Array,
    markers: Array,
    horizon: float,
    odo_end: float,
    timeout: float,
    max_epochs: int,
) -> tuple[NDArray[np.int64], bool]:
    """Navigator._plan: epochs end at the first sample at or after t_prev + period (or at the
    given epoch_times), cut at the first pending marker passage (markers: sorted times, s);
    an epoch waits for its samples (horizon s: stamp time up to which all data are in) and,
    up to timeout s, for odometer coverage (odo_end: the last odometer stamp). Returns the
    ends and whether the last epoch has a marker due (planning stops there)."""
    ends = np.empty(max_epochs, dtype=np.int64)
    nb = 0
    t_prev = t0
    due = False
    while nb < max_epochs:
        if epoch_times.shape[0] > 0:
            i = np.searchsorted(epoch_times, t_prev + 1e-9, side="right")
            target = epoch_times[i] - 1e-9 if i < epoch_times.shape[0] else np.inf
            end = np.searchsorted(t, target)
        else:
            end = np.searchsorted(t, t_prev + period - 1e-9)
            j = np.searchsorted(markers, t_prev, side="right")  # the first pending marker
            if j < markers.shape[0]:
                end = min(end, np.searchsorted(t, markers[j]))
        if end >= t.shape[0]:
            break
        t_end = t[end]
        if horizon < t_end or (odo_end < t_end and horizon < t_end + timeout):
            break
        ends[nb] = end
        nb += 1
        t_prev = t_end
        if markers.shape[0] > 0 and markers[0] <= t_end:
            due = True
            break
    return ends[:nb], due


def _flat_states(states: Sequence[NavState] | Array | None) -> Array | None:
    """States as a (K, SV_SIZE) array (NavState.vector rows)."""
    if states is None:
        return None
    if isinstance(states, np.ndarray):
        return np.ascontiguousarray(states, dtype=np.float64)
    return np.array([s.vector() for s in states]).reshape(-1, SV_SIZE)


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
