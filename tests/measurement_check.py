"""Helpers of the measurement tests: a random state and the check of a Jacobian against
finite differences of its residual (the filter, the backward filter and the smoothers all
linearize the same, correct model only if every H is right)."""

import math

import numpy as np
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.model.state import Layout, NavState

MODES = ["ins", "dr"]


def random_state(rng: np.random.Generator) -> NavState:
    return NavState(
        t=10.0,
        lat=math.radians(31.0),
        lon=math.radians(114.0),
        h=25.0,
        vel_n=rng.normal(0, 1.5, 3),
        q_nb=att.quat_from_euler(rng.uniform(-3, 3), rng.uniform(-0.5, 0.5), rng.uniform(0, 6)),
        bg=rng.normal(0, 1e-3, 3),
        ba=rng.normal(0, 1e-2, 3),
        k=0.01,
        bore=np.array([0.01, -0.02]),
    )


def check_jacobian(
    residual, s: NavState, layout: Layout, H: np.ndarray, eps: float = 1e-6, tol: float = 2e-5
) -> None:
    r0 = residual(s)
    num = np.zeros_like(H)
    for j in range(layout.n):
        d = np.zeros(layout.n)
        d[j] = eps
        rp = residual(s.inject(d, layout))
        d[j] = -eps
        rm = residual(s.inject(d, layout))
        num[:, j] = -(rp - rm) / (2 * eps)
    scale = max(1.0, float(np.abs(H).max()))
    np.testing.assert_allclose(H, num, atol=tol * scale, err_msg=f"r0={r0}")
