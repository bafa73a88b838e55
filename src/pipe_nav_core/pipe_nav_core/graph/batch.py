"""The batch (factor-graph) smoother: Gauss-Newton over the whole run with a robust loss on the
marker factors, started from a smoothed trajectory (the RTS solution).

Each iteration linearizes the whole problem about the current trajectory X
(:func:`.linearize.linearize`: the filter's own transition, process noise and measurement
kernels), weighs the factors (:func:`factor_weights`: Huber IRLS weights on the markers, the
filter's chi-square gate on the others, both on the residual at X), solves every epoch's
correction at once (:func:`.solver.solve_chain`) and moves X by it (its turn of the initial
heading as an exact rotation about the first marker, :func:`.rotation.retract`). A step that
raises the robust cost and is not followed by a smaller one is retried at half its length (at
most MAX_HALVINGS times in a row: a line search in its simplest form). It stops when a step is
below CONVERGED_POS_M and CONVERGED_RAD.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..config import NavConfig
from ..kalman import chi2_threshold
from ..state import Layout, layout_for
from ..types import SensorLog, markers_sorted
from .linearize import FactorRecorder, linearize
from .problem import LinearChain
from .robust import HUBER_K, huber_cost, huber_weight
from .rotation import Pivot, retract
from .solver import ChainSolution, WhitenedFactors, solve_chain, whiten

Array = NDArray[np.float64]

MAX_ITERATIONS = 10  # Gauss-Newton iterations (linearizations) at most
MAX_HALVINGS = 4  # step halvings of one iteration at most when the robust cost rises
# a step below these ends the iterations (the iterated smoother's thresholds,
# pipe_nav_core.smoother; the step is applied: what remains is of second order in it)
CONVERGED_POS_M = 0.01  # m: largest position step of a converged iteration
CONVERGED_RAD = 1e-4  # rad: largest attitude step of a converged iteration


@dataclass
class Weighing:
    """Factor weights of one linearization and what they did: weights (F,) (0: left out);
    downweighted: names of the robust factors (markers) with weight < 1; gated: factors left
    out per kind; robust_cost: the objective at the linearization point (prior and between
    terms plus the robust loss of the measurements, dimensionless)."""

    weights: Array
    downweighted: list[str] = field(default_factory=list)
    gated: dict[str, int] = field(default_factory=dict)
    robust_cost: float = math.nan


def factor_weights(
    chain: LinearChain,
    gate_probability: float,
    huber_k: float = HUBER_K,
    whitened: WhitenedFactors | None = None,
) -> tuple[Array, list[str], dict[str, int], Array]:
    """IRLS weights of the factors at the linearization point: Huber weights on the robust
    ones (markers), and for the others 1, or 0 when their whitened squared residual exceeds
    the chi-square quantile of gate_probability (the filter's gate, here on the residual of
    the current trajectory rather than on the innovation); exact factors (MeasurementFactor.exact)
    keep weight 1 and add nothing to the loss. Returns (weights, names of the downweighted
    robust factors, gated count per kind, the robust loss per factor)."""
    wf = whitened if whitened is not None else whiten(chain.factors, chain.n)
    F = len(chain.factors)
    w = np.ones(F)
    loss = np.zeros(F)
    down: list[str] = []
    gated: dict[str, int] = {}
    gates = {m: chi2_threshold(gate_probability, m) for m in (1, 2, 3)}
    for i, f in enumerate(chain.factors):
        if wf.exact[i]:  # a constraint: weight 1, and no part in the cost steps are judged on
            continue
        e = float(wf.norm[i])
        if f.robust:
            w[i] = float(huber_weight(e, huber_k))
            loss[i] = float(huber_cost(e, huber_k))
            if w[i] < 1.0:
                down.append(f.name or f"{f.kind}@{f.epoch}")
            continue
        m = len(f.r)
        gate = gates[m] if m in gates else chi2_threshold(gate_probability, m)
        if not e * e <= gate:
            w[i] = 0.0
            gated[f.kind] = gated.get(f.kind, 0) + 1
        else:
            loss[i] = e * e
    return w, down, gated, loss


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
        """The smoothed corrections in the form pipe_nav_core.smoother._centreline takes:
        relative to the pass's filter estimate (its x_upd), (K, n)."""
        rec = self.nav.recording
        assert rec is not None
        return self.solution.delta - rec.x_upd


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
) -> GraphResult:
    """Gauss-Newton on the batch problem of a time-sorted log from reference (flat states
    (K, SV_SIZE) at the epochs of an earlier pass, e.g. the RTS solution; see the module
    docstring). odometer_exclude: (N, 2) s intervals without odometer speed factors (slips);
    reverse: the log runs in reversed time (the Navigator's reverse)."""
    layout = layout_for(config)
    markers = markers_sorted(log.markers)
    pivot: Pivot | None = (markers[0].lat, markers[0].lon, markers[0].alt) if markers else None
    X = np.array(reference, dtype=np.float64)
    history: list[float] = []
    best_cost = math.inf
    X_prev: Array | None = None
    delta_prev: Array | None = None
    step_prev = (math.inf, math.inf)
    halvings = 0
    it = 0
    while True:
        it += 1
        say(f"graph: linearizing about the trajectory (iteration {it})")
        chain, nav = linearize(log, config, X, odometer_exclude=odometer_exclude, reverse=reverse)
        wf = whiten(chain.factors, chain.n)
        w, down, gated, loss = factor_weights(chain, config.gate_probability, huber_k, wf)
        say(f"graph: solving {chain.K} epochs, {len(chain.factors)} factors")
        sol = solve_chain(chain, w, whitened=wf)
        quad = float(np.sum(w * wf.norm**2))
        cost = sol.cost0 - quad + float(loss.sum())  # the robust objective at X
        history.append(cost)
        weighing = Weighing(w, down, gated, cost)
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
            del chain, nav, wf, sol  # before the next linearization is built
            continue
        halvings = 0
        best_cost = min(best_cost, cost)
        converged = step[0] < CONVERGED_POS_M and step[1] < CONVERGED_RAD
        if converged or it >= max_iterations:
            states = retract(X, sol.delta, layout, pivot)
            return GraphResult(nav, sol, states, it, converged, history, weighing)
        X_prev, delta_prev, step_prev = X, sol.delta, step
        X = retract(X, sol.delta, layout, pivot)
        del chain, nav, wf, sol  # before the next linearization is built
