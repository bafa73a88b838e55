"""The batch (factor-graph) smoother: Gauss-Newton over the whole run with a robust loss on the
marker factors, started from a smoothed trajectory (the RTS solution).

Each iteration linearizes the whole problem about the current trajectory X
(:class:`.linearize.FactorRecorder`: the filter's own transition, process noise and
measurement kernels), weighs the factors (:func:`factor_weights_of`: Huber IRLS weights on the
markers, the filter's chi-square gate on the others, both on the residual at X), solves every
epoch's correction at once, eliminating epoch by epoch as the linearization goes
(:class:`StreamingSolve`, :class:`.solver.Eliminator`: the problem is never held whole, so
memory does not grow with the run beyond a few arrays of K rows; the epochs are whitened PIECE
at a time and eliminated on a worker thread while the linearization fills the next piece) and
moves X by it (its turn
of the initial heading as an exact rotation about the first marker, :func:`.rotation.retract`).
A step that raises the robust cost and is not followed by a smaller one is retried at half its
length (at most MAX_HALVINGS times in a row: a line search in its simplest form). It stops
when a step is below CONVERGED_POS_M and CONVERGED_RAD.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.kalman import chi2_threshold
from pipe_nav_core.graph.linearize import FactorRecorder
from pipe_nav_core.graph.problem import Factors, LinearChain, MeasurementFactor, Prior
from pipe_nav_core.graph.robust import HUBER_K, huber_cost, huber_weight
from pipe_nav_core.graph.rotation import Pivot, retract
from pipe_nav_core.graph.solver import (
    PIECE,
    ChainSolution,
    Eliminator,
    WhitenedFactors,
    whiten,
    whiteners,
)
from pipe_nav_core.model.state import Layout, layout_for
from pipe_nav_core.smooth.forward import feed
from pipe_nav_core.types import SensorLog, markers_sorted

Array = NDArray[np.float64]
Index = NDArray[np.int64]

# the elimination runs on a worker thread beside the linearization (StreamingSolve)
OVERLAP = True
MAX_ITERATIONS = 10  # Gauss-Newton iterations (linearizations) at most
MAX_HALVINGS = 4  # step halvings of one iteration at most when the robust cost rises
# a step below these ends the iterations (the iterated smoother's thresholds,
# pipe_nav_core.smooth.passes; the step is applied: what remains is of second order in it)
CONVERGED_POS_M = 0.01  # m: largest position step of a converged iteration
CONVERGED_RAD = 1e-4  # rad: largest attitude step of a converged iteration


@dataclass
class Weighing:
    """What the factor weights of one linearization did: downweighted: names of the robust
    factors (markers) with weight < 1; gated: factors left out per kind; robust_cost: the
    objective at the linearization point (prior and between terms plus the robust loss of
    the measurements, dimensionless)."""

    downweighted: list[str] = field(default_factory=list)
    gated: dict[str, int] = field(default_factory=dict)
    robust_cost: float = math.nan

    def note(self, f: Factors, i: int, weight: float) -> None:
        """Count factor i of f (not an exact one) with its weight."""
        if f.robust[i] and weight < 1.0:
            self.downweighted.append(str(f.name[i]) or f"{f.kind[i]}@{f.epoch[i]}")
        elif not f.robust[i] and weight == 0.0:
            kind = str(f.kind[i])
            self.gated[kind] = self.gated.get(kind, 0) + 1


def factor_weights_of(
    factors: Factors,
    wf: WhitenedFactors,
    gate_probability: float,
    huber_k: float = HUBER_K,
) -> tuple[Array, Array]:
    """IRLS weights (F,) and robust losses (F,) of factors whose whitened residual norms at
    the linearization point are wf.norm (:func:`.solver.whiten` of them): the Huber weight and
    loss on a robust factor (marker); for the others weight 1 and loss e^2, or weight 0 (and
    no loss) when e^2 exceeds the chi-square gate for its rows (the filter's gate, here on the
    residual of the current trajectory rather than on the innovation); an exact factor
    (MeasurementFactor.exact) is a constraint: weight 1, and no part in the cost the steps
    are judged on."""
    e, exact = wf.norm, wf.exact
    robust, sizes = factors.robust, factors.m
    gate = np.zeros(len(factors))
    for m in np.unique(sizes):
        gate[sizes == m] = chi2_threshold(gate_probability, int(m))
    e2 = e * e
    inside = e2 <= gate
    w = np.where(robust, huber_weight(e, huber_k), np.where(inside, 1.0, 0.0))
    loss = np.where(robust, huber_cost(e, huber_k), np.where(inside, e2, 0.0))
    w[exact], loss[exact] = 1.0, 0.0
    return w, loss


def factor_weights(
    chain: LinearChain,
    gate_probability: float,
    huber_k: float = HUBER_K,
    whitened: WhitenedFactors | None = None,
) -> tuple[Array, Weighing, Array]:
    """:func:`factor_weights_of` every factor of a chain: (weights (F,), what they did, the
    robust loss per factor (F,))."""
    fs = Factors.of(chain.factors, chain.n)
    wf = whitened if whitened is not None else whiten(fs, chain.n)
    w, loss = factor_weights_of(fs, wf, gate_probability, huber_k)
    out = Weighing()
    for i in np.flatnonzero(~wf.exact):
        out.note(fs, int(i), float(w[i]))
    return w, out, loss


class StreamingSolve:
    """An :class:`~.linearize.EpochSink` that weighs each factor (:func:`factor_weights_of`) and
    eliminates epoch by epoch (:class:`~.solver.Eliminator`): the Gauss-Newton iteration's
    solve without keeping the problem. Epochs are taken PIECE at a time: their
    between-factors and measurements are whitened at once (:func:`.solver.whiteners`,
    :func:`.solver.whiten`: one batched Cholesky factor and inverse per PIECE epochs, not one
    per epoch and factor), then eliminated in order. :meth:`finish` returns the solution and
    the weighing (its robust cost included)."""

    def __init__(
        self,
        n: int,
        gate_probability: float,
        huber_k: float = HUBER_K,
        overlap: bool | None = None,
    ) -> None:
        self.n = n
        self.gate_probability = gate_probability
        self.huber_k = huber_k
        overlap = OVERLAP if overlap is None else overlap
        self.weighing = Weighing()
        self._quad = 0.0  # sum of w e^2: the measurements' part of the weighted cost
        self._loss = 0.0  # sum of their robust loss
        self._elim = Eliminator(n)
        self.K = 0  # epochs taken
        # the epochs taken and not yet eliminated, in blocks: phi, qd (B, n, n), offset (B, n),
        # their factors and how many of them each epoch has (B,)
        self._phi: list[Array] = []
        self._qd: list[Array] = []
        self._offset: list[Array] = []
        self._factors: list[Factors] = []
        self._counts: list[Index] = []
        self._pending = 0  # epochs in those blocks
        # the elimination of full pieces runs on one worker thread while the linearization
        # goes on (LAPACK releases the GIL), in order; overlap=False: on the caller's thread
        self._pool = (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix="graph-eliminate")
            if overlap
            else None
        )
        self._running: Future[None] | None = None

    def _weigh(self, factors: Factors) -> tuple[Array, Array, Array]:
        """The weighted whitened rows (M, n) and right-hand sides (M,) of factors (in their
        order, which is epoch order; factors of weight 0 left out), and where each factor's
        rows start (F + 1,). The weights are `factor_weights_of`'s, for all factors at once."""
        wf = whiten(factors, self.n)  # sorted by epoch, stably: rows in the factors' order
        w, loss = factor_weights_of(factors, wf, self.gate_probability, self.huber_k)
        for i in np.flatnonzero(~wf.exact & (w < 1.0)):  # what the weights did, in order
            self.weighing.note(factors, int(i), float(w[i]))
        self._quad += float(np.sum(w * (wf.norm * wf.norm)))
        self._loss += float(np.sum(loss))
        # a weight w divides the noise covariance: it scales the whitened rows by sqrt(w);
        # a factor of weight 0 is left out
        scale = np.repeat(np.sqrt(w[wf.order]), np.diff(wf.start))
        keep = scale > 0.0
        start = np.r_[0, np.cumsum(keep)][wf.start]
        return wf.rows[keep] * scale[keep, None], wf.rhs[keep] * scale[keep], start

    def start(self, prior: Prior, factors: Factors | list[MeasurementFactor]) -> None:
        fs = factors if isinstance(factors, Factors) else Factors.of(factors, self.n)
        rows, rhs, _ = self._weigh(fs)
        self._elim.first(prior.x0, prior.P0, rows, rhs)
        self.K = 1

    def epoch(self, phi: Array, qd: Array, offset: Array, factors: list[MeasurementFactor]) -> None:
        """The next epoch: :meth:`epochs` of one, its factors a list."""
        self.epochs(phi[None], qd[None], offset[None], Factors.of(factors, self.n))

    def epochs(self, phi: Array, qd: Array, offset: Array, factors: Factors) -> None:
        """The next B epochs (K .. K + B - 1, K the epochs taken so far): their
        between-factors phi, qd (B, n, n), offset (B, n) and their factors (epochs in that
        range, in epoch order); the arrays are kept, not copied."""
        B = len(phi)
        self._phi.append(phi)
        self._qd.append(qd)
        self._offset.append(offset)
        self._factors.append(factors)
        self._counts.append(np.bincount(factors.epoch - self.K, minlength=B))
        self.K += B
        self._pending += B
        if self._pending >= PIECE:
            self._flush()

    def _flush(self) -> None:
        """Hand the pending epochs to the elimination (:meth:`_eliminate`): on the worker
        thread when there is one, after the piece before (so at most one piece waits while the
        linearization fills the next)."""
        if not self._phi:
            return
        piece = (self._phi, self._qd, self._offset, self._factors, self._counts)
        self._phi, self._qd, self._offset, self._factors, self._counts = [], [], [], [], []
        self._pending = 0
        if self._pool is None:
            self._eliminate(*piece)
            return
        self._wait()
        self._running = self._pool.submit(self._eliminate, *piece)

    def _wait(self) -> None:
        """Wait for the piece being eliminated on the worker thread (raising its error)."""
        running, self._running = self._running, None
        if running is not None:
            running.result()

    def _eliminate(
        self,
        phi: list[Array],
        qd: list[Array],
        offset: list[Array],
        factors: list[Factors],
        counts: list[Index],
    ) -> None:
        """Whiten and weigh a piece of epochs (blocks of them) at once, then eliminate them in
        order."""
        W = whiteners(np.concatenate(qd))
        WPhi = W @ np.concatenate(phi)
        Wo = np.einsum("bij,bj->bi", W, np.concatenate(offset))
        rows, rhs, start = self._weigh(Factors.join(factors, self.n))
        # rows of epoch j of the piece: at[j] .. at[j+1]
        at = start[np.r_[0, np.cumsum(np.concatenate(counts))]]
        for j in range(len(W)):
            s = slice(at[j], at[j + 1])
            self._elim.add_whitened(WPhi[j], W[j], Wo[j], rows[s], rhs[s])

    def _stop_worker(self) -> None:
        """Wait for the worker thread's piece (its error ignored) and end the thread."""
        running, self._running = self._running, None
        if running is not None:
            running.exception()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def close(self) -> None:
        """Free the eliminator's rows without solving."""
        self._phi, self._qd, self._offset, self._factors, self._counts = [], [], [], [], []
        self._pending = 0
        self._stop_worker()
        self._elim.close()

    def finish(self) -> tuple[ChainSolution, Weighing]:
        try:
            self._flush()
            self._wait()
        except BaseException:
            self.close()
            raise
        self._stop_worker()
        sol = self._elim.finish()
        self.weighing.robust_cost = sol.cost0 - self._quad + self._loss
        return sol, self.weighing


def _step(delta: Array, layout: Layout) -> tuple[float, float]:
    """Largest position (m) and attitude (rad) correction of a step."""
    pos = float(np.max(np.linalg.norm(delta[:, layout.pos], axis=1)))
    att = float(np.max(np.linalg.norm(delta[:, layout.att], axis=1)))
    return pos, att


@dataclass
class GraphResult:
    """Result of :func:`graph_smooth`.

    nav: the last linearization's pass (its recording carries the per-sample nominal; its
    reference is the trajectory the last step started from); solution: the last solve
    (delta relative to nav's reference, marginal variances); states: the final trajectory,
    flat (K, SV_SIZE); iterations: linearizations solved; converged: the last step was below
    the thresholds; history: the robust cost at each linearization; weighing: the last
    linearization's factor weights.
    """

    nav: FactorRecorder
    solution: ChainSolution
    states: Array
    iterations: int
    converged: bool
    history: list[float]
    weighing: Weighing

    def corrections(self) -> Array:
        """The smoothed corrections in the form
        :func:`pipe_nav_core.smooth.centreline.smoothed_centreline` takes: relative to the
        pass's filter estimate (its x_upd), the columns ``pose`` (position m, attitude rad) of
        its recording, (K, 6)."""
        rec = self.nav.recording
        assert rec is not None
        return self.solution.delta[:, rec.pose] - rec.x_upd_pose


def graph_smooth(
    log: SensorLog,
    config: NavConfig,
    reference: Array,
    *,
    odometer_exclude: Array | None = None,
    reverse: bool = False,
    max_iterations: int = MAX_ITERATIONS,
    huber_k: float = HUBER_K,
    say: Callable[[str], None] = lambda _msg: None,
    straight: tuple[Array, Array] | None = None,
) -> GraphResult:
    """Gauss-Newton on the batch problem of a time-sorted log from reference (flat states
    (K, SV_SIZE) at the epochs of an earlier pass, e.g. the RTS solution; see the module
    docstring). odometer_exclude: (N, 2) s intervals without odometer speed factors (slips);
    reverse: the log runs in reversed time (the Navigator's reverse); straight: the straight
    sections (plan, vertical: chainage intervals (K, 2), m) for every iteration (None: each
    iteration's from its own linearization point)."""
    layout = layout_for(config)
    markers = markers_sorted(log.markers)
    pivot: Pivot | None = (markers[0].lat, markers[0].lon, markers[0].alt) if markers else None
    X = np.asarray(reference, dtype=np.float64)  # not copied (0.17 GB at 100 km): only read
    history: list[float] = []
    best_cost = math.inf
    X_prev: Array | None = None
    delta_prev: Array | None = None
    step_prev = (math.inf, math.inf)
    halvings = 0
    it = 0
    while True:
        it += 1
        say(f"graph: linearizing and solving about the trajectory (iteration {it})")
        stream = StreamingSolve(layout.n, config.gate_probability, huber_k)
        nav = FactorRecorder(
            config, log.markers, reference=X, odometer_exclude=odometer_exclude,
            reverse=reverse, sink=stream, straight=straight,
        )  # fmt: skip
        try:
            feed(nav, log, config, release=True)  # in slices: not the whole log copied at once
        except BaseException:
            stream.close()
            raise
        if nav.state is None:
            stream.close()
            raise ValueError("no navigation solution: no usable IMU data after alignment")
        sol, weighing = stream.finish()
        cost = weighing.robust_cost  # the robust objective at X
        history.append(cost)
        step = _step(sol.delta, layout)
        # a step that raised the cost is kept if the next one is smaller (a large first step
        # from far off often raises it on the way into the basin: the iterated smoother's
        # passes take such steps too); else it is retried at half its length
        rising = cost > best_cost * (1.0 + 1e-9) + 1e-9
        shrinking = step[0] < step_prev[0] or step[1] < step_prev[1]
        retry = rising and not shrinking and halvings < MAX_HALVINGS
        if retry and X_prev is not None and delta_prev is not None:
            halvings += 1
            delta_prev = 0.5 * delta_prev
            step_prev = (0.5 * step_prev[0], 0.5 * step_prev[1])
            X = retract(X_prev, delta_prev, layout, pivot)
            del nav, sol  # before the next linearization is built
            continue
        halvings = 0
        best_cost = min(best_cost, cost)
        converged = step[0] < CONVERGED_POS_M and step[1] < CONVERGED_RAD
        if converged or it >= max_iterations:
            states = retract(X, sol.delta, layout, pivot)
            return GraphResult(nav, sol, states, it, converged, history, weighing)
        X_prev, delta_prev, step_prev = X, sol.delta, step
        X = retract(X, sol.delta, layout, pivot)
        del nav, sol  # before the next linearization is built
