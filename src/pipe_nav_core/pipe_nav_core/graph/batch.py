"""The batch (factor-graph) smoother: Gauss-Newton over the whole run with a robust loss on the
marker factors, started from a smoothed trajectory (the RTS solution).

Each iteration linearizes the whole problem about the current trajectory X
(:func:`.linearize.linearize`: the filter's own transition, process noise and measurement
kernels), weighs the factors (:func:`factor_weights`: Huber IRLS weights on the markers, the
filter's chi-square gate on the others, both on the residual at X), solves every epoch's
correction at once (:func:`.solver.solve_chain`) and moves X by it. A step that raises the
robust cost is halved (at most MAX_HALVINGS times; Levenberg-Marquardt's safeguard in its
simplest form). It stops when a step is below the iterated smoother's convergence thresholds
(:data:`pipe_nav_core.smoother.CONVERGED_POS_M`, :data:`~pipe_nav_core.smoother.CONVERGED_RAD`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..config import NavConfig
from ..kalman import chi2_threshold
from ..state import Layout, inject_many, layout_for
from ..types import SensorLog
from .linearize import FactorRecorder, linearize
from .problem import LinearChain
from .robust import HUBER_K, huber_cost, huber_weight
from .solver import ChainSolution, solve_chain

Array = NDArray[np.float64]

MAX_ITERATIONS = 10  # Gauss-Newton iterations (linearizations) at most
MAX_HALVINGS = 4  # step halvings of one iteration at most when the robust cost rises
CONVERGED_POS_M = 0.001  # m: largest position step of a converged iteration
CONVERGED_RAD = 1e-5  # rad: largest attitude step of a converged iteration


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
    chain: LinearChain, gate_probability: float, huber_k: float = HUBER_K
) -> tuple[Array, list[str], dict[str, int], Array]:
    """IRLS weights of the factors at the linearization point: Huber weights on the robust
    ones (markers), and for the others 1, or 0 when their whitened squared residual exceeds
    the chi-square quantile of gate_probability (the filter's gate, here on the residual of
    the current trajectory rather than on the innovation). Returns (weights, names of the
    downweighted robust factors, gated count per kind, the robust loss per factor)."""
    F = len(chain.factors)
    w = np.ones(F)
    loss = np.zeros(F)
    down: list[str] = []
    gated: dict[str, int] = {}
    for i, f in enumerate(chain.factors):
        e = f.whitened_norm()
        if f.robust:
            w[i] = float(huber_weight(e, huber_k))
            loss[i] = float(huber_cost(e, huber_k))
            if w[i] < 1.0:
                down.append(f.name or f"{f.kind}@{f.epoch}")
        elif not e * e <= chi2_threshold(gate_probability, len(f.r)):
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
    X = np.array(reference, dtype=np.float64)
    history: list[float] = []
    best_cost = math.inf
    X_prev: Array | None = None
    delta_prev: Array | None = None
    halvings = 0
    it = 0
    while True:
        it += 1
        say(f"graph: linearizing about the trajectory (iteration {it})")
        chain, nav = linearize(log, config, X, odometer_exclude=odometer_exclude, reverse=reverse)
        w, down, gated, loss = factor_weights(chain, config.gate_probability, huber_k)
        say(f"graph: solving {chain.K} epochs, {len(chain.factors)} factors")
        sol = solve_chain(chain, w)
        quad = sum(float(w[i]) * chain.factors[i].whitened_norm() ** 2 for i in range(len(w)))
        cost = sol.cost0 - quad + float(loss.sum())  # the robust objective at X
        history.append(cost)
        weighing = Weighing(w, down, gated, cost)
        rising = cost > best_cost * (1.0 + 1e-9) + 1e-9
        if rising and X_prev is not None and delta_prev is not None and halvings < MAX_HALVINGS:
            halvings += 1  # the last step overshot: retry half of it
            delta_prev = 0.5 * delta_prev
            X = inject_many(X_prev, delta_prev, layout)
            continue
        halvings = 0
        best_cost = min(best_cost, cost)
        pos, att = _step(sol.delta, layout)
        converged = pos < CONVERGED_POS_M and att < CONVERGED_RAD
        if converged or it >= max_iterations:
            states = inject_many(X, sol.delta, layout)
            return GraphResult(nav, sol, states, it, converged, history, weighing)
        X_prev, delta_prev = X, sol.delta
        X = inject_many(X, sol.delta, layout)
