"""The batch problem linearized about a trajectory, built from the filter's own epoch.

:class:`FactorRecorder` is the :class:`~pipe_nav_core.filter.navigator.Navigator` run about a
reference trajectory (the iterated smoother's pass: same alignment prior, same epochs, same inputs,
same odometer exclusions), which also writes down, epoch by epoch, what its compiled epoch
linearizes: the transition Phi_k, the process noise Qd_k and the offset (mechanization from
X_{k-1} minus X_k) of every between-factor, from :func:`pipe_nav_core.filter.epoch.run_epochs`
itself (a prediction from zero error and zero covariance returns exactly those), and every
measurement the epoch would apply, as a :class:`~.problem.MeasurementFactor` evaluated by the
same kernel of :mod:`pipe_nav_core.model.measurements` with the same inputs, preconditions, gates
and row splits: each measurement's ``factors`` front end runs the same compiled policy as the
``apply`` that :func:`epoch._updates` calls. Handing the problem to a sink (the Gauss-Newton
iteration's solve), the batches of epochs without a marker run in one compiled call instead
(:func:`pipe_nav_core.filter.epoch.linearize_epochs`), whose factors are the updates as the
filter's own :func:`~pipe_nav_core.model.measurements.context.update` records them: the same
arrays, bytes for bytes (tested), without a Python call per epoch.

The chi-square gates on the innovation are not applied here (they depend on the forward
filter's covariance): the batch solver gates and weighs the factors itself (:mod:`.batch`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.epoch import (
    Batch,
    EpochOutputs,
    Filter,
    Inputs,
    Settings,
    context,
    linearize_epochs,
    run_epochs,
)
from pipe_nav_core.filter.navigator import Navigator, PassOptions
from pipe_nav_core.graph.problem import Factors, LinearChain, MeasurementFactor, Model, Prior
from pipe_nav_core.model import measurements
from pipe_nav_core.smooth.recording import Recording, phi_rows
from pipe_nav_core.types import Marker, SensorLog

Array = NDArray[np.float64]
Index = NDArray[np.int64]

KIND_NAMES = np.array(measurements.KINDS, dtype=np.str_)  # the update kinds, by their index


class EpochSink(Protocol):
    """Receives the linearized problem a block of epochs at a time, in order, instead of the
    recorder keeping it (a solver that eliminates as it goes: memory independent of the run's
    length)."""

    def start(self, prior: Prior, factors: Factors) -> None:
        """The prior on epoch 0 and epoch 0's factors."""

    def epochs(self, phi: Array, qd: Array, offset: Array, factors: Factors) -> None:
        """The next B epochs' between-factors (phi, qd (B, n, n), offset (B, n)) and their
        factors (arrays the sink keeps)."""


class FactorRecorder(Navigator):
    """A Navigator pass about ``reference`` (flat states (K, SV_SIZE) at the epochs of an
    earlier pass over the same data) that records the batch problem linearized about it:
    :meth:`problem` after :meth:`Navigator.run`, or, with a ``sink``, hands it over a batch of
    epochs at a time and keeps none of it. Its recording (``recording``) is the pass's, for
    the centreline at the IMU rate (:func:`pipe_nav_core.smooth.centreline.smoothed_centreline`);
    with a sink it keeps only what the centreline is made of (``Recording`` centreline_only:
    nothing here reads the pass's covariances, states or steps)."""

    def __init__(
        self,
        config: NavConfig,
        survey: Sequence[Marker] = (),
        *,
        reference: Array,
        odometer_exclude: Array | None = None,
        reverse: bool = False,
        sink: EpochSink | None = None,
        straight: tuple[Array, Array] | None = None,
    ) -> None:
        super().__init__(
            config,
            survey,
            PassOptions(record=True, emit=False, reverse=reverse, reference=reference,
                        odometer_exclude=odometer_exclude, straight=straight),
        )  # fmt: skip
        self.sink = sink
        if sink is not None:
            self.report.recording = Recording(self.layout, reference=self.reference,
                                              centreline_only=True)  # fmt: skip
        K, n = (0 if sink is not None else len(reference)), self.layout.n
        # the rows of Phi that can differ from the identity's, and the rows of Qd that can be
        # more than diagonal: those of the attitude, velocity and position errors (the nonzero
        # rows of the system matrix, process.discretize_k)
        self.phi_rows = phi_rows(self.layout)
        self.qd_rows = np.arange(self.layout.pos.stop)
        self.phi = np.zeros((K, len(self.phi_rows), n))
        self.phi[:, np.arange(len(self.phi_rows)), self.phi_rows] = 1.0
        self.qd = np.zeros((K, len(self.qd_rows), n))
        self.qd_diag = np.zeros((K, n))
        self.offset = np.zeros((K, n))
        # what _store_transition checks is not lost: the identity's rows of Phi, and Qd's
        # entries off its diagonal outside qd_rows
        rest = np.setdiff1d(np.arange(n), self.phi_rows)
        self._phi_rest, self._eye_rest = rest, np.eye(n)[rest]
        q = np.setdiff1d(np.arange(n), self.qd_rows)
        qi, qj = np.meshgrid(q, q, indexing="ij")
        off = qi != qj
        self._qd_off = (qi[off], qj[off])
        self.factors: list[MeasurementFactor] = []
        self.prior: Prior | None = None
        self._scratch: Batch | None = None
        self._buffers: EpochOutputs | None = None  # the scratch batch's (Batch.buffers)
        self._f: Filter | None = None
        self._pending: tuple[Array, Array, Array] = (np.zeros(0), np.zeros(0), np.zeros(0))

    # ------------------------------------------------------------------ hooks
    def _align(self, idx: Array) -> None:
        super()._align(idx)
        assert self.kf is not None
        self.prior = Prior(self.kf.x.copy(), self.kf.P.copy())
        if self.sink is not None:
            self.sink.start(self.prior, Factors.of([], self.layout.n))

    def _call(
        self,
        batch: Batch,
        inputs: Inputs,
        markers: Array,
        *,
        stop: bool = False,
        resume: bool = False,
    ) -> None:
        self._record(inputs, markers, stop, resume)
        super()._call(batch, inputs, markers, stop=stop, resume=resume)

    def _call_ahead(self, batch: Batch, inputs: Inputs) -> None:
        self._record(inputs, np.zeros((0, 7)), False, False)
        super()._call_ahead(batch, inputs)

    def _record(self, inputs: Inputs, markers: Array, stop: bool, resume: bool) -> None:
        """The linearization of the epochs a call of the compiled loop runs, before it."""
        if self.sink is not None and not (stop or resume or len(markers)):
            self._linearize_batch(inputs)
        else:
            self._linearize(inputs, markers, stop, resume)

    # ------------------------------------------------------------------ the problem
    def problem(self) -> LinearChain:
        """The linearized batch problem of the epochs run so far (not with a sink: it took
        the problem)."""
        if self.sink is not None:
            raise ValueError("the problem went to the sink, epoch by epoch")
        if self.prior is None or self.recording is None:
            raise ValueError("no navigation solution: the pass never aligned")
        K = len(self.recording)
        return LinearChain(
            self.prior, self.phi[:K], self.qd[:K], self.qd_diag[:K], self.offset[:K],
            self.phi_rows, self.qd_rows, list(self.factors),
        )  # fmt: skip

    def _scratch_for(self, samples: int, epochs: int = 1) -> Batch:
        """The scratch batch, for this many IMU samples and epochs (room for every update
        of them recorded), cleared."""
        b = self._scratch
        if b is None or len(b.lat) < samples or len(b.sv) < epochs:
            size = max(epochs, 1 if b is None else len(b.sv))
            b = self._scratch = Batch(size, max(samples, 256), self.layout.n,
                                      factors=size * len(measurements.KINDS))  # fmt: skip
            self._buffers = b.buffers()
        b.reset()
        return b

    def _linearize_batch(self, inputs: Inputs) -> None:
        """The epochs of a batch without markers in one compiled call
        (:func:`pipe_nav_core.filter.epoch.linearize_epochs`: each from zero error and
        covariance on a scratch copy of the filter's memory, as :meth:`_linearize` runs them
        one at a time), handed to the sink at once: their transitions, process noises,
        offsets, and as factors the updates the filter would apply, recorded by its own
        update (ungated)."""
        assert self._prm is not None and self.reference is not None and self.sink is not None
        n, B = self.layout.n, len(inputs.ends)
        k0 = self._epoch + 1
        f = Filter(
            self._sv.copy(), np.zeros(n), np.zeros((n, n)), self._carry.copy(),
            self._dyn.copy(), self._dyn_i.copy(),
        )  # fmt: skip
        sb = self._scratch_for(int(inputs.ends[-1]) + 1, B)
        offset = np.empty((B, n))
        linearize_epochs(k0, f, self.layout.index, self._prm, self.reference, inputs,
                         sb.buffers(), offset)  # fmt: skip
        F = int(sb.fac_n[0])
        if len(sb.fac) < F:
            raise RuntimeError(f"{F} updates in {B} epochs: more than the scratch records")
        fac, info = sb.fac[:F], sb.fac_i[:F]
        kind = KIND_NAMES[info[:, 0]]
        factors = Factors(
            kind, info[:, 2] + k0, info[:, 1].copy(), fac[:, :, n].copy(), fac[:, :, :n].copy(),
            fac[:, :, n + 1 :].copy(), kind == "marker", np.full(F, "", dtype=np.str_),
        )  # fmt: skip
        self.sink.epochs(sb.phi[:B].copy(), sb.P_pred[:B].copy(), offset, factors)

    def _linearize(self, inputs: Inputs, markers: Array, stop: bool, resume: bool) -> None:
        """Each epoch of a batch once more, one at a time, from zero error and covariance on
        a scratch copy of the filter's memory (its mechanization carry and the previous
        epoch's speed and velocity, which do not depend on the error state): the prediction
        gives Phi, Qd and the offset, then the factors are read off the epoch's inputs."""
        assert self._prm is not None
        L, prm = self.layout.index, self._prm
        ref = self.reference
        assert ref is not None
        n = self.layout.n
        if not resume or self._f is None:
            self._f = Filter(
                self._sv.copy(), np.zeros(n), np.zeros((n, n)), self._carry.copy(),
                self._dyn.copy(), self._dyn_i.copy(),
            )  # fmt: skip
        f = self._f
        ends = inputs.ends
        B = len(ends)
        no_markers = np.zeros((0, 7))
        for e in range(B):
            k = self._epoch + 1 + e
            i0 = int(ends[e - 1]) + 1 if e else 0
            i1 = int(ends[e]) + 1
            one = Inputs(
                inputs.imu_t[i0:i1], inputs.imu_g[i0:i1], inputs.imu_a[i0:i1],
                np.array([i1 - i0 - 1], dtype=np.int64), inputs.s_odo[i0:i1],
                inputs.has_odo[e : e + 1], inputs.still[e : e + 1], inputs.excluded[e : e + 1],
                inputs.resolution[e : e + 1], inputs.mag_i[e : e + 1], inputs.mag_t,
                inputs.mag_f,
            )  # fmt: skip
            if resume and e == 0:
                sb = self._scratch
                assert sb is not None
            else:
                sb = self._scratch_for(i1 - i0)
                f.x[:] = 0.0
                f.P[:] = 0.0
                assert self._buffers is not None
                run_epochs(True, False, False, 0, 1, k, f, L, prm, ref, one, no_markers,
                           self._buffers)  # fmt: skip
                if self.sink is not None:
                    self._pending = (sb.phi[0].copy(), sb.P_pred[0].copy(), sb.ws_x.copy())
                else:
                    self._store_transition(k, sb.phi[0], sb.P_pred[0], sb.ws_x)
            if stop and e == B - 1:
                return
            mk = markers if e == B - 1 else no_markers
            first = len(self.factors)
            self._factors_of_epoch(k, sb, one, f, prm, mk)
            if self.sink is not None:  # epoch k is complete: hand it over
                phi, qd, offset = self._pending
                self.sink.epochs(phi[None], qd[None], offset[None],
                                 Factors.of(self.factors[first:], n))  # fmt: skip
                del self.factors[first:]
            sb.marker_res = np.zeros((len(mk), 3))
            bufs = self._buffers
            assert bufs is not None
            bufs = self._buffers = bufs._replace(marker_res=sb.marker_res)
            run_epochs(False, True, False, 0, 1, k, f, L, prm, ref, one, mk, bufs)

    def _store_transition(self, k: int, phi: Array, qd: Array, offset: Array) -> None:
        """Epoch k's transition phi (n, n), process noise qd (n, n) (predicted from zero
        covariance) and offset (n,) (predicted from zero error), compactly (LinearChain)."""
        if not np.array_equal(phi[self._phi_rest], self._eye_rest) or np.any(qd[self._qd_off]):
            raise ValueError("the transition or process noise has more than the stored rows")
        self.phi[k] = phi[self.phi_rows]
        self.qd[k] = qd[self.qd_rows]
        self.qd_diag[k] = np.diagonal(qd)
        self.offset[k] = offset

    def _factors_of_epoch(
        self, k: int, sb: Batch, inp: Inputs, f: Filter, prm: Settings, markers: Array
    ) -> None:
        """The measurements epoch._updates applies at epoch k, with its inputs and gates (but
        not its innovation gate), as factors evaluated at the linearization point."""
        c = context(sb.ws, sb.ws_i, sb.ws_sv, sb.ws_m, f.dyn, f.dyn_i, self.layout.index, prm,
                    inp.imu_t, sb.q, inp.mag_t, inp.mag_f, markers)  # fmt: skip
        rows = iter(markers)
        for kind, model in measurements.factors(c):
            if kind == "marker":
                name = self._marker_name(next(rows))
                self._add(kind, k, c.s, model, robust=True, name=name)
            else:
                self._add(kind, k, c.s, model)

    def _add(
        self, kind: str, k: int, s: Array, model: Model, *, robust: bool = False, name: str = ""
    ) -> None:
        r, H, R = model(s, self.layout.index)
        self.factors.append(MeasurementFactor(kind, k, r, H, R, model, robust, name))

    def _marker_name(self, vec: Array) -> str:
        for m in (*self.survey, *self.inbox.markers_seen):
            if m.t == vec[0] and m.lat == vec[1] and m.lon == vec[2]:
                return m.name
        return ""


def linearize(
    log: SensorLog,
    config: NavConfig,
    reference: Array,
    *,
    odometer_exclude: Array | None = None,
    reverse: bool = False,
) -> tuple[LinearChain, FactorRecorder]:
    """The batch problem of a time-sorted log linearized about reference (flat states
    (K, SV_SIZE) at the epochs of an earlier pass of the engine over the same log, from the
    alignment on), and the pass that built it (its recording holds the per-sample nominal)."""
    nav = FactorRecorder(
        config, log.markers, reference=reference, odometer_exclude=odometer_exclude,
        reverse=reverse,
    )  # fmt: skip
    nav.run(log)
    if nav.state is None:
        raise ValueError("no navigation solution: the log has no usable IMU data after alignment")
    return nav.problem(), nav
