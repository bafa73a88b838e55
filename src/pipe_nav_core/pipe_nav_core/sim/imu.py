"""IMU error model: what a real gyro triad and accelerometer triad add to the ideal signal.

Per axis, for each sensor (gyro rad/s, accelerometer m/s^2), in the sensor frame imu_link:

    y = M x + b_on + b_gm(t) + n,      M = I + diag(scale) + misalignment (off-diagonal),

with b_on a random constant (turn-on bias), b_gm a first-order Gauss-Markov process (bias
instability sigma, correlation time tau; stationary start), n white noise with per-sample sigma
density / sqrt(dt) (the output is a mean over dt, so an angle/velocity random walk of the given
density), and optional quantisation of the integrated increment (angle or velocity quantum; the
remainder is carried so that no drift is created). The model is stateful so that a long run can
be generated in chunks with exactly the same result as in one piece.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from pipe_nav_core.model.sensors import ImuSpec

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TriadErrors:
    """Realised constant errors of one sensor triad (truth, for diagnostics only).

    turn_on_bias: (3,) rad/s or m/s^2; matrix: (3, 3) M = I + scale + misalignment
    (dimensionless); gm_bias0: (3,) initial Gauss-Markov bias.
    """

    turn_on_bias: FloatArray
    matrix: FloatArray
    gm_bias0: FloatArray


def _children(rng: np.random.Generator, n: int) -> list[np.random.Generator]:
    """n independent generators derived deterministically from rng (works on numpy >= 1.17)."""
    entropy = [int(x) for x in rng.integers(0, 2**63, size=4)]
    return [np.random.default_rng(c) for c in np.random.SeedSequence(entropy).spawn(n)]


class _Triad:
    """Stateful error generator of one triad (internal)."""

    def __init__(
        self,
        rng: np.random.Generator,
        dt: float,
        white_density: float,
        bias_instability: float,
        corr_time: float,
        turn_on: float,
        scale: float,
        misalignment: float,
        quantum: float,
    ) -> None:
        self.dt = dt
        consts, self._noise_rng, self._gm_rng = _children(rng, 3)
        on = consts.standard_normal(3) * turn_on
        m = np.eye(3) + np.diag(consts.standard_normal(3) * scale)
        off = consts.standard_normal((3, 3)) * misalignment
        np.fill_diagonal(off, 0.0)
        m = m + off
        gm0 = consts.standard_normal(3) * bias_instability
        self.errors = TriadErrors(on, m, gm0)
        self._sigma_white = white_density / math.sqrt(dt)
        if bias_instability > 0.0 and corr_time > 0.0:
            self._phi = math.exp(-dt / corr_time)
            self._q = bias_instability * math.sqrt(max(1.0 - self._phi**2, 0.0))
        else:
            self._phi, self._q = 0.0, 0.0
        self._gm_state = gm0.copy()
        self.quantum = quantum
        self._carry = np.zeros(3)  # integrated increment not yet output, in quanta units * q

    def apply(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Errors added to the ideal chunk x (n, 3). Returns (measured, Gauss-Markov bias)."""
        n = x.shape[0]
        y = x @ self.errors.matrix.T
        y += self.errors.turn_on_bias
        if self._q > 0.0:
            w = self._gm_rng.standard_normal((n, 3)) * self._q
            zi = (self._phi * self._gm_state)[None, :]
            gm, _ = lfilter([1.0], [1.0, -self._phi], w, axis=0, zi=zi)
            self._gm_state = gm[-1].copy() if n else self._gm_state
            y += gm
        else:
            gm = np.broadcast_to(self._gm_state, (n, 3))
            y += gm
        if self._sigma_white > 0.0:
            y += self._noise_rng.standard_normal((n, 3)) * self._sigma_white
        if self.quantum > 0.0 and n:
            inc = y * self.dt
            cum = self._carry + np.cumsum(inc, axis=0)
            q_cum = np.round(cum / self.quantum) * self.quantum
            prev = np.vstack([np.zeros((1, 3)), q_cum[:-1]])
            y = (q_cum - prev) / self.dt
            self._carry = cum[-1] - q_cum[-1]
        return y, np.asarray(gm)


class ImuErrorModel:
    """Gyro and accelerometer error generators for one run.

    spec: ImuSpec (SI units); dt: s sample interval; rng: numpy Generator (consumed only here).
    """

    def __init__(self, spec: ImuSpec, dt: float, rng: np.random.Generator) -> None:
        g_rng, a_rng = _children(rng, 2)
        self.spec = spec
        self.gyro = _Triad(
            g_rng,
            dt,
            spec.gyro_arw,
            spec.gyro_bias_instability,
            spec.gyro_bias_corr_time,
            spec.gyro_turn_on_bias,
            spec.gyro_scale_factor,
            spec.gyro_misalignment,
            spec.gyro_quantization,
        )
        self.accel = _Triad(
            a_rng,
            dt,
            spec.accel_vrw,
            spec.accel_bias_instability,
            spec.accel_bias_corr_time,
            spec.accel_turn_on_bias,
            spec.accel_scale_factor,
            spec.accel_misalignment,
            spec.accel_quantization,
        )

    def apply(
        self, gyro: FloatArray, accel: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Measured (gyro rad/s, accel m/s^2) for the ideal chunk, both (n, 3) in imu_link, and
        the Gauss-Markov biases (n, 3) of each (truth)."""
        g, gb = self.gyro.apply(gyro)
        a, ab = self.accel.apply(accel)
        return g, a, gb, ab
