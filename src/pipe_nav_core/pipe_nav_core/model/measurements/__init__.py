"""Measurements: one module per measurement, shared by the forward filter, the backward filter
and the smoothers.

Each module owns everything of its measurement:
- its model, a compiled kernel ``*_k(sv, L, ...)`` on a flat state and layout index array
  (:mod:`pipe_nav_core.model.state`) returning (residual r = z - h(x_hat) (m,), H (m, n) with
  r ~= H dx + noise for the error state dx = truth - estimate, R (m, m) in the measurement's
  units), and a NavState wrapper of it for tests;
- ``inputs_k(c)``: its policy at an epoch (:class:`~.context.Context`): preconditions, gates,
  noise, returning whether it applies and the model's inputs;
- ``apply(c, x, P, out)``: the compiled epoch's call: the policy, then the model at the
  linearization point, split into its updates (rows), each through :func:`.context.update`
  (chi-square gate, Joseph update, statistics), and the gate's events counted;
- ``factors(c)``: the same updates, from the same policy, as models of the state for the batch
  solver (:mod:`pipe_nav_core.graph.linearize`).

Frames: ENU navigation frame, base_link body frame (FLU). Units SI, angles rad.

Adding a measurement: write its module as the others (kernel, inputs_k, apply, factors), add
its kind to KINDS (and any setting to P_* and epoch.parameters) in :mod:`.context`, call its
``apply`` in :func:`pipe_nav_core.filter.epoch._updates` and list it in ORDER below, at the same
place (the order of the updates; a test checks the two agree).
"""

from __future__ import annotations

from pipe_nav_core.model.measurements import (
    gravity_tilt,
    magnetic_heading,
    marker,
    odometer,
    zero_rate,
    zero_velocity,
)
from pipe_nav_core.model.measurements.context import Context, Factor, Measurement

# the updates of an epoch, in the order epoch._updates applies them
ORDER = (odometer, zero_velocity, zero_rate, gravity_tilt, magnetic_heading, marker)

__all__ = ["ORDER", "Context", "Factor", "Measurement", "factors"]


def factors(c: Context) -> list[Factor]:
    """Every update the compiled epoch applies at this context, in its order, as models."""
    return [f for module in ORDER for f in module.factors(c)]
