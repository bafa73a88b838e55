"""The navigation filter: one object used identically by the live node, the bag replay and
the offline smoother's passes.

Feed samples (``push_*`` one at a time in any order within the reorder window, or
:meth:`Navigator.run` with a time-sorted :class:`~pipe_nav_core.types.SensorLog`), collect
:class:`~pipe_nav_core.filter.estimates.NavEstimate` s (one per filter epoch) with
:meth:`Navigator.poll`. A smoother pass (:class:`PassOptions`) keeps what the smoothers need
(:class:`~pipe_nav_core.smooth.recording.Recording`).

Processing: static alignment (:mod:`~pipe_nav_core.filter.alignment`) -> per epoch
(``filter_rate_hz``, :mod:`~pipe_nav_core.filter.planner`): mechanize the IMU samples (INS or DR),
propagate the covariance, then gated updates: odometer speed + non-holonomic constraint (INS),
zero velocity and zero rate at stops, gravity tilt, magnetic heading, marker fixes, with the
heading re-anchored at the second marker when it comes from the markers
(:mod:`~pipe_nav_core.filter.anchoring`). This class composes those parts: samples in
(:mod:`~pipe_nav_core.filter.ingest`), epochs run, estimates out
(:mod:`~pipe_nav_core.filter.estimates`).
"""

from __future__ import annotations

import math
import threading
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.background import Background
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter import alignment
from pipe_nav_core.filter.anchoring import FreeHeading, HeadingAnchor
from pipe_nav_core.filter.epoch import (
    D_FREE,
    D_INT_SIZE,
    D_S_START,
    D_SIZE,
    S_LIN,
    W_VJAC,
    Batch,
    Filter,
    Inputs,
    Settings,
    parameters,
    run_epochs,
    transition_epochs,
)
from pipe_nav_core.filter.estimates import NavEstimate, Reporter, model_warnings
from pipe_nav_core.filter.ingest import Inbox
from pipe_nav_core.filter.kalman import ErrorStateKF
from pipe_nav_core.filter.odometer_resolution import OdometerResolution
from pipe_nav_core.filter.planner import BatchPool, Ends, epoch_inputs, plan, tally
from pipe_nav_core.model import imu_noise as imu_model
from pipe_nav_core.model.measurements.marker import marker_vector
from pipe_nav_core.model.measurements.straight_pipe import NO_SECTIONS, sections
from pipe_nav_core.model.state import SV_SIZE, SV_T, NavState, layout_for
from pipe_nav_core.smooth.recording import Recording
from pipe_nav_core.types import Datum, Marker, SensorLog, markers_sorted

Array = NDArray[np.float64]
# epochs whose transitions are made at a time on the other core about a reference trajectory
# (Navigator._call_ahead): small enough that the first costs little waiting, large enough that
# the handing over costs little
AHEAD_SPAN = 32


@dataclass(frozen=True, eq=False)
class PassOptions:
    """How a smoother's pass differs from the live filter (the default).

    record: keep the smoothers' data (:attr:`Navigator.recording`); emit: produce estimates;
    reverse: the data are time-reversed (the backward filter of the two-filter smoother);
    initial: a state whose attitude azimuth, biases, odometer scale and boresight replace the
    static-alignment values (the re-linearization pass); epoch_times: s, force the epoch ends
    to the first IMU samples at or after these times instead of filter_rate_hz and marker
    passages (the backward filter uses the forward filter's epochs); odometer_exclude: (N, 2)
    time intervals (s) whose odometer speed is not used (slips found by a previous pass);
    reference: a trajectory (one NavState, or flat state (SV_SIZE,), per epoch from the
    alignment on, at the epoch times of an earlier pass over the same data) about which every
    Jacobian, transition and measurement residual is linearized instead of about the filter's
    own estimate; the prior stays the static alignment's and the filter carries its mean
    error relative to the reference. Smoothing such a pass and feeding the result back as the
    next reference is one Gauss-Newton step of the batch problem (iterated smoother,
    :mod:`pipe_nav_core.smooth.passes`); the epoch ends are then the reference's times, and
    the straight-pipe and section-direction updates take their straight sections from it
    (:func:`~pipe_nav_core.model.measurements.straight_pipe.sections`).
    straight: the chainage intervals (m; plan, vertical plane: (K, 2) each) straight in the
    pipe, for a pass without a reference of its own (two-filter's backward filter, mapped
    from its forward pass's reference); without them, a pass about a reference takes its own.
    initial_azimuth: rad, replaces the initial heading of the configured source (the
    smoother iterates the re-anchoring at the second marker with it); free_heading: keep the
    initial heading's prior outside the filter until the next marker after the first
    (:class:`~pipe_nav_core.filter.anchoring.FreeHeading`); None: while the heading from the markers
    is unanchored (the live filter). Not for a pass the RTS smooths: to it the prior's return
    at that marker is process noise.
    """

    record: bool = False
    emit: bool = True
    reverse: bool = False
    initial: NavState | None = None
    epoch_times: Array | None = None
    odometer_exclude: Array | None = None
    reference: Sequence[NavState] | Array | None = field(default=None, repr=False)
    straight: tuple[Array, Array] | None = field(default=None, repr=False)
    initial_azimuth: float | None = None
    free_heading: bool | None = None

    @property
    def earth_sign(self) -> float:
        """-1 for time-reversed data (the Earth turns the other way), else 1."""
        return -1.0 if self.reverse else 1.0


LIVE = PassOptions()


class Navigator:
    """The online estimator (see the module docstring).

    config: estimator settings; survey: surveyed markers known in advance (their passage times
    may be unknown); options: a smoother's pass (:class:`PassOptions`), default the live
    filter.

    Jacobians that couple attitude and velocity are evaluated at a first-estimate velocity
    (the predicted one, zero when stopped, or the reference's) so that a rotation of the whole
    solution about the vertical stays unobservable between markers, as it is: evaluating them
    at the freshly corrected velocity makes an EKF believe it learns its heading from odometer
    and zero-velocity noise.
    """

    def __init__(
        self, config: NavConfig, survey: Sequence[Marker] = (), options: PassOptions = LIVE
    ) -> None:
        config.validate()
        self.cfg = config
        self.options = options
        self.layout = layout_for(config)
        self.imu_spec = config.imu_spec()
        # imu_grade auto: the noise model is chosen from the initial rest at the alignment
        # (imu_model.choose_at_rest), or from these per-sample variances the Imu messages
        # declare ({"gyro_variance": 3 x (rad/s)^2, "accel_variance": 3 x (m/s^2)^2}), which
        # the caller may set before the data; imu_choice says what was chosen and why.
        self.declared_imu_noise: dict[str, list[float]] | None = None
        self.imu_choice: imu_model.ImuModelChoice | None = None
        self.survey = markers_sorted(survey)
        ex = options.odometer_exclude
        ex = np.zeros((0, 2)) if ex is None else np.asarray(ex, float)
        self.odometer_exclude = ex[np.argsort(ex[:, 0], kind="stable")].reshape(-1, 2)
        self.reference = _flat_states(options.reference)
        times = options.epoch_times
        self.epoch_times = None if times is None else np.sort(np.asarray(times, float))
        if self.reference is not None:
            self.epoch_times = self.reference[:, SV_T].copy()
        self.reset()

    # ----------------------------------------------------------------- public API
    def reset(self) -> None:
        """Forget everything: back to waiting for the static alignment."""
        cfg, opt = self.cfg, self.options
        self._counts: defaultdict[str, int] = defaultdict(int)
        self.inbox = Inbox(cfg, self._counts, self.survey[0] if self.survey else None)
        self.resolution = OdometerResolution(cfg.odometer_resolution)
        anchored = cfg.heading_source != "markers" or self.reference is not None
        self.anchor = HeadingAnchor(cfg, self.layout, anchored, self._counts)
        self.report = Reporter(cfg, self.layout, emit=opt.emit, record=opt.record,
                               reference=self.reference)  # fmt: skip
        self._pool = BatchPool(self.layout.n, double=opt.record,
                               transitions=self.reference is not None)  # fmt: skip
        self.state: NavState | None = None
        self.kf: ErrorStateKF | None = None
        # the filter's memory as the compiled epoch keeps it (epoch.Filter)
        self._sv = np.zeros(SV_SIZE)
        self._carry = np.zeros(6)
        self._dyn = np.zeros(D_SIZE)
        self._dyn_i = np.zeros(D_INT_SIZE, dtype=np.int64)
        self._prm: Settings | None = None
        self._epoch = 0  # epochs run since the alignment
        self.initial_azimuth: float | None = None  # rad, the alignment's
        # s: no position before this (aligned before any marker: placed at 0, 0 until one is
        # passed; inf until then)
        self.positioned_at = -math.inf

    @property
    def datum(self) -> Datum | None:
        """The first marker (surveyed, else the first passed): the estimates' local frame."""
        m = self.inbox.first_marker
        return Datum(m.lat, m.lon, m.alt) if m is not None else None

    @property
    def recording(self) -> Recording | None:
        """What the smoothers need (PassOptions.record), else None."""
        return self.report.recording

    @property
    def free_heading(self) -> FreeHeading | None:
        """The initial heading's prior kept outside the filter, or None."""
        return self.anchor.free_heading

    @property
    def reanchor_rad(self) -> float:
        """rad: the rotation of the heading re-anchoring at the second marker (0 before)."""
        return self.anchor.reanchor_rad

    @property
    def inflated_markers(self) -> list[str]:
        """The markers whose passage inflated the covariance, in order: each disagreed with
        the filter beyond its gate (HeadingAnchor.before_marker)."""
        return list(self.anchor.inflated)

    @property
    def after_odometer_loss(self) -> list[str]:
        """The markers the filter reached having lost the odometer, in order (it had rejected
        ODOMETER_LOST_FRACTION or more of the speed updates since the passage before:
        HeadingAnchor)."""
        return list(self.anchor.after_odometer_loss)

    @property
    def odometer_resolution(self) -> float:
        """Encoder resolution (m per count) in use: configured or learnt so far (0 = none)."""
        return self.resolution.value

    @property
    def reorder_horizon(self) -> float:
        """Stamp (s) up to which samples have left the reorder window: a sample stamped at or
        before it would be late (dropped and counted)."""
        return float(self.inbox.reorder.horizon)

    def push_imu(self, t: float, gyro: Sequence[float], accel: Sequence[float]) -> None:
        """One IMU sample: stamp s, mean rate rad/s and mean specific force m/s^2, imu_link."""
        sample = self.inbox.imu_sample(t, gyro, accel)
        if sample is not None:
            self._push(t, "imu", sample)

    def push_odometer(self, t: float, distance: float, speed: float) -> None:
        """One odometer sample: cumulative distance m and speed m/s."""
        sample = self.inbox.odometer_sample(t, distance, speed)
        if sample is not None:
            self._push(t, "odometer", sample)

    def push_mag(self, t: float, field_t: Sequence[float]) -> None:
        """One magnetometer sample, tesla, imu_link."""
        sample = self.inbox.mag_sample(t, field_t)
        if sample is not None:
            self._push(t, "mag", sample)

    def push_marker(self, marker: Marker) -> None:
        """One marker passage."""
        if self.inbox.marker_sample(marker) is not None:
            self._push(marker.t, "marker", marker)

    def poll(self) -> list[NavEstimate]:
        """Estimates produced since the last call, in time order."""
        return self.report.poll()

    def finish(self) -> list[NavEstimate]:
        """End of data: release and process everything still buffered."""
        self.inbox.flush()
        self._advance()
        return self.poll()

    def run(self, log: SensorLog, *, final: bool = True) -> None:
        """Offline fast path: ingest a time-sorted log (or consecutive chunks of one; pass
        final=False for all but the last chunk). Identical results to pushing the samples."""
        self.inbox.add_log(log, final)
        self._advance()

    def diagnostics(self) -> dict[str, int | float | str]:
        """Counters: samples per topic, dropped and late samples, accepted/rejected updates."""
        d: dict[str, int | float | str] = dict(self._counts)
        for kind, n in self.inbox.reorder.late.items():
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

    def model_warnings(self) -> list[str]:
        """Signs that the IMU noise model does not fit the data so far
        (:func:`~pipe_nav_core.filter.estimates.model_warnings`); empty when it fits."""
        bg = self.state.bg if self.state is not None else np.zeros(0)
        return model_warnings(self.diagnostics(), bg, self.imu_spec)

    # ----------------------------------------------------------------- processing
    def _push(self, t: float, kind: str, payload: object) -> None:
        """A checked sample into the reorder window; the epochs it completes run."""
        if self.inbox.push(t, kind, payload):
            self._advance()

    def _advance(self) -> None:
        """Align, then run every epoch the buffered data complete."""
        while True:
            if self.state is None:
                ib = self.inbox
                idx = alignment.rest_window(ib.imu_t, ib.odo, ib.first_marker,
                                            self.cfg.static_alignment_s, ib.horizon)  # fmt: skip
                if idx is None:
                    return
                self._align(idx)
                continue
            ends, marker_due, still = plan(self.inbox, self.state.t,
                                           1.0 / self.cfg.filter_rate_hz, self.epoch_times,
                                           self.cfg.stop_speed_threshold)  # fmt: skip
            if not len(ends):
                return
            if marker_due:
                if len(ends) > 1:
                    self._run_batch(ends[:-1], still[:-1])
                    ends = ends[-1:] - (ends[-2] + 1)  # the buffer now starts after ends[-2]
                self._run_marker_epoch(ends, still[-1:])
            else:
                self._run_batch(ends, still)

    def _align(self, idx: NDArray[np.intp]) -> None:
        """The static alignment over the IMU samples idx of the buffer, and the filter's start
        (about the reference's first state when linearized about one)."""
        cfg, lay, ib = self.cfg, self.layout, self.inbox
        a = alignment.align(
            cfg, lay, (ib.imu_t[idx], ib.imu_g[idx], ib.imu_a[idx]), ib.mag, ib.first_marker,
            self.survey, self.options, self.anchor.anchored, self.declared_imu_noise,
            lambda t: self.resolution.at(ib.odo, t),
        )  # fmt: skip
        self.imu_choice, self.imu_spec = a.imu_choice, a.imu_spec
        self.initial_azimuth = a.azimuth
        if ib.first_marker is None:
            self.positioned_at = math.inf
        self.anchor.free_heading = a.free_heading
        s = a.state
        if self.reference is not None:
            # the prior stays the alignment's; only the linearization point moves
            lin = NavState.from_vector(self.reference[0])
            if abs(lin.t - s.t) > 1e-6:
                raise ValueError("the reference trajectory does not start at the alignment epoch")
            lin.distance = 0.0
            self.kf = ErrorStateKF(a.P0, cfg.gate_probability, s.difference(lin, lay))
            s = lin.inject(self.kf.x, lay)
        else:
            self.kf = ErrorStateKF(a.P0, cfg.gate_probability)
        self.state = s
        self._sv = s.vector()
        self._carry = np.zeros(6)
        self._dyn = np.zeros(D_SIZE)
        self._dyn[D_S_START] = float(ib.odometer_at(np.array([s.t]))[0])
        self._dyn_i = np.zeros(D_INT_SIZE, dtype=np.int64)
        self._dyn_i[D_FREE] = not self.anchor.anchored
        earth_sign = self.options.earth_sign
        straight = self.options.straight
        if straight is None:
            straight = (NO_SECTIONS, NO_SECTIONS) if self.reference is None else tuple(sections(
                self.reference, cfg, self.imu_spec.gyro_arw)[:2])  # fmt: skip
        self._prm = parameters(cfg, self.imu_spec, np.asarray(cfg.odometer_lever_arm, float),
                               earth_sign, a.mag_ref, straight)  # fmt: skip
        self._counts["aligned_at_ms"] = int(round(s.t * 1000))
        ib.drop_before(s.t)
        self.report.alignment(self._sv, self.kf, self.anchor.free_heading)

    def _call(
        self,
        batch: Batch,
        inputs: Inputs,
        markers: Array,
        *,
        stop: bool = False,
        resume: bool = False,
    ) -> None:
        """One call of the compiled epoch loop on the filter's memory (epoch.run_epochs):
        stop after the first epoch's prediction, or resume from it (a marker epoch)."""
        kf = self.kf
        assert kf is not None and self._prm is not None
        ref = self.reference if self.reference is not None else np.empty((0, SV_SIZE))
        state = Filter(self._sv, kf.x, kf.P, self._carry, self._dyn, self._dyn_i)
        run_epochs(
            stop, resume, False, 0, len(inputs.ends), self._epoch + 1, state, self.layout.index,
            self._prm, ref, inputs, markers, batch.buffers(),
        )  # fmt: skip

    def _inputs(self, ends: Ends, still: NDArray[np.bool_]) -> Inputs:
        assert self.state is not None
        return epoch_inputs(
            self.inbox, self.state.t, ends, self.odometer_exclude, self.resolution, still
        )

    def _run_batch(self, ends: Ends, still: NDArray[np.bool_]) -> None:
        """Epochs without a marker passage (``still``: plan's), all in one call of the compiled
        loop (about a reference trajectory, on two cores: :meth:`_call_ahead`)."""
        batch = self._pool.get(len(ends), int(ends[-1]) + 1)
        if self.reference is not None and len(ends) > AHEAD_SPAN:
            self._call_ahead(batch, self._inputs(ends, still))
        else:
            self._call(batch, self._inputs(ends, still), np.zeros((0, 7)))
        self._finish(batch, ends)

    def _call_ahead(self, batch: Batch, inputs: Inputs) -> None:
        """Epochs without a marker passage about the reference trajectory, on two cores: a
        thread makes their transitions (epoch.transition_epochs, AHEAD_SPAN epochs at a time;
        about a reference they depend on the reference and the data alone) while this one
        propagates the error state through them and applies the updates (run_epochs with
        ``ready``): the same arithmetic as :meth:`_call`'s, in two halves."""
        kf, prm, ref = self.kf, self._prm, self.reference
        assert kf is not None and prm is not None and ref is not None
        B, k0, L, out = len(inputs.ends), self._epoch + 1, self.layout.index, batch.buffers()
        carry, dyn, dyn_i = self._carry.copy(), self._dyn.copy(), self._dyn_i.copy()
        spans = [(a, min(a + AHEAD_SPAN, B)) for a in range(0, B, AHEAD_SPAN)]
        made = threading.Semaphore(0)
        failed: list[bool] = []

        def make() -> None:
            try:
                for a, b in spans:
                    transition_epochs(a, b, k0, self._sv, carry, dyn, dyn_i, L, prm, ref,
                                      inputs, out)  # fmt: skip
                    made.release()
            except BaseException:
                failed.append(True)
                made.release(len(spans))  # the waiting below ends; result() raises
                raise

        job = Background("pipe-nav transitions", make)
        state = Filter(self._sv, kf.x, kf.P, self._carry, self._dyn, self._dyn_i)
        no_markers = np.zeros((0, 7))
        for a, b in spans:
            made.acquire()
            if failed:
                break
            run_epochs(False, False, True, a, b, k0, state, L, prm, ref, inputs, no_markers, out)
        job.result()
        self._carry[:] = carry  # the last epoch's, as _call leaves it

    def _run_marker_epoch(self, ends: Ends, still: NDArray[np.bool_]) -> None:
        """The epoch of a marker passage (``still``: plan's): prediction, then (Python) the
        heading re-anchoring and the covariance recovery (HeadingAnchor.before_marker), then
        the updates with the marker fix."""
        kf = self.kf
        assert kf is not None and self.state is not None
        due = self.inbox.take_markers(self.inbox.imu_t[ends[-1]])
        batch = Batch(1, int(ends[-1]) + 1, self.layout.n)
        inputs = self._inputs(ends, still)
        self._call(batch, inputs, np.zeros((0, 7)), stop=True)
        s = NavState.from_vector(batch.ws_sv[S_LIN])
        due = [m for m in due if not self.anchor.late(m, s)]
        v_jac = batch.ws[W_VJAC : W_VJAC + 3]
        for m in due:
            s, rz = self.anchor.before_marker(kf, s, m, self.inbox.first_marker)
            v_jac[:] = rz @ v_jac  # the first-estimate velocity turns with the re-anchored state
        batch.ws_sv[S_LIN] = s.vector()
        batch.ws_x[:] = kf.x  # the prediction as before_marker left it
        batch.P_pred[0] = kf.P
        mk = np.array([marker_vector(m) for m in due]).reshape(-1, 7)
        if due and self.positioned_at == math.inf:
            self.positioned_at = s.t
        batch.marker_res = np.zeros((len(due), 3))
        self._call(batch, inputs, mk, resume=True)
        if self.recording is not None:
            for m, r in zip(due, batch.marker_res, strict=True):
                self.recording.marker_residuals[m.name] = r.copy()
        self._dyn_i[D_FREE] = not self.anchor.anchored
        self._finish(batch, ends)

    def _finish(self, batch: Batch, ends: Ends) -> None:
        """Take a batch's results: state, counters, recording, estimates; drop its samples."""
        assert self.kf is not None
        self.state = NavState.from_vector(self._sv)
        tally(batch, self._counts, self.kf.stats)
        self.report.batch(batch, ends, self.inbox.imu_t, self.anchor.free_heading)
        self._epoch += len(ends)
        self.inbox.drop_before(self.state.t)


def _flat_states(states: Sequence[NavState] | Array | None) -> Array | None:
    """States as a (K, SV_SIZE) array (NavState.vector rows)."""
    if states is None:
        return None
    if isinstance(states, np.ndarray):
        return np.ascontiguousarray(states, dtype=np.float64)
    return np.array([s.vector() for s in states]).reshape(-1, SV_SIZE)
