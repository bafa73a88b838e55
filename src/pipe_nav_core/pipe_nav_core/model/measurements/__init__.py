"""Measurements: one module per measurement, shared by the forward filter, the backward filter
and the smoothers, registered in MEASUREMENTS below.

Each module owns everything of its measurement:
- ``KINDS``: the names of its updates (rows of the update statistics) and ``EVENTS``: the
  names of the events its gates count;
- its model, a compiled kernel ``*_k(sv, L, ...)`` on a flat state and layout index array
  (:mod:`pipe_nav_core.model.state`) returning (residual r = z - h(x_hat) (m,), H (m, n) with
  r ~= H dx + noise for the error state dx = truth - estimate, R (m, m) in the measurement's
  units), and a NavState wrapper of each update for tests;
- ``inputs_k(c)``: its policy at an epoch (:class:`~.context.Context`): preconditions, gates,
  noise, returning whether it applies and the model's inputs;
- ``apply(c, x, P, tally, kind, event)``: the compiled epoch's call: the policy, then the
  model at the linearization point, split into its updates, each through
  :func:`.context.update` (chi-square gate, Joseph update, statistics in the
  :class:`~.context.Tally` under ``kind`` + its place in KINDS), and the gates' events counted
  (under ``event`` + its place in EVENTS);
- ``factors(c)``: the same updates, from the same policy, as models of the state for the batch
  solver (:mod:`pipe_nav_core.graph.linearize`).

Frames: ENU navigation frame, base_link body frame (FLU). Units SI, angles rad.

Adding a measurement: write its module as the others (KINDS, EVENTS, kernel, inputs_k, apply,
factors; a new setting goes into :class:`.context.Settings` and epoch.parameters) and list it
in MEASUREMENTS below, where it is applied in the epoch's order. The epoch's update sequence
(UPDATES, unrolled by numba into straight calls), the statistics' kinds and counters and the
batch solver's factors all derive from that one line.
"""

from __future__ import annotations

from pipe_nav_core.model.measurements import (
    gravity_tilt,
    magnetic_heading,
    marker,
    odometer,
    section_direction,
    straight_pipe,
    zero_rate,
    zero_velocity,
)
from pipe_nav_core.model.measurements.context import Context, Factor, Measurement, Settings

# the measurements, in the order the epoch applies them
MEASUREMENTS = (
    odometer,
    zero_velocity,
    zero_rate,
    straight_pipe,
    section_direction,
    gravity_tilt,
    magnetic_heading,
    marker,
)

KINDS = tuple(k for m in MEASUREMENTS for k in m.KINDS)  # rows of the update statistics
C_EPOCHS = 0  # the epoch's own counter, then the measurements' events
COUNTERS = ("epochs", *(e for m in MEASUREMENTS for e in m.EVENTS))


def _updates() -> tuple[tuple[int, int, object], ...]:
    """(where its KINDS start, where its EVENTS start, its apply) of each measurement, in
    order (the apply last: a tuple led by a function makes numba try to unify functions)."""
    out, kind, event = [], 0, C_EPOCHS + 1
    for m in MEASUREMENTS:
        out.append((kind, event, m.apply))
        kind, event = kind + len(m.KINDS), event + len(m.EVENTS)
    return tuple(out)


UPDATES = _updates()  # epoch._updates calls each in turn (numba.literal_unroll)

__all__ = [
    "C_EPOCHS",
    "COUNTERS",
    "KINDS",
    "MEASUREMENTS",
    "UPDATES",
    "Context",
    "Factor",
    "Measurement",
    "Settings",
    "factors",
]


def factors(c: Context) -> list[Factor]:
    """Every update the compiled epoch applies at this context, in its order, as models."""
    return [f for module in MEASUREMENTS for f in module.factors(c)]
