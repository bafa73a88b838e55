"""Magnetometer inside a steel pipe.

The Earth's field (declination D east of true north, inclination I positive downwards, magnitude
B in tesla) in local ENU is ``B [cos I sin D, cos I cos D, -sin I]``. Inside the pipe the sensor
sees it attenuated by the scalar relative-permeability factor mu (seed 001 eq. 10, 31), plus
localized anomalies at the girth welds (remanent magnetisation, a Gaussian bump along the
chainage with a fixed random direction per weld), the pig's own hard iron (constant in imu_link)
and white noise. Samples are instantaneous (not interval means).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def earth_field_enu(declination: float, inclination: float, magnitude: float) -> FloatArray:
    """Earth field vector (3,) in ENU, tesla, from declination (rad, east of true north
    positive), inclination (rad, positive downwards) and magnitude (T)."""
    ci = math.cos(inclination)
    return magnitude * np.array(
        [ci * math.sin(declination), ci * math.cos(declination), -math.sin(inclination)]
    )


class WeldField:
    """Anomalies at girth welds at chainages ``welds`` (m): each a field (T, ENU) ``vectors[k]``
    times exp(-0.5 ((s - welds[k]) / width)^2)."""

    def __init__(self, welds: FloatArray, vectors: FloatArray, width: float) -> None:
        self.welds = np.asarray(welds, dtype=np.float64).reshape(-1)
        self.vectors = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
        self.width = float(width)

    @classmethod
    def draw(
        cls,
        rng: np.random.Generator,
        length: float,
        spacing: float,
        amplitude: float,
        width: float,
        jitter: float = 0.3,
    ) -> WeldField:
        """Welds every ``spacing`` m (+- jitter m) along ``length`` m, anomaly vectors with
        random direction and magnitude amplitude * U(0.5, 1.5) (T), Gaussian width ``width`` m."""
        if spacing <= 0.0 or amplitude <= 0.0 or length <= spacing:
            return cls(np.empty(0), np.empty((0, 3)), max(width, 1e-3))
        welds = np.arange(spacing, length, spacing)
        welds = welds + rng.uniform(-jitter, jitter, welds.shape)
        d = rng.standard_normal((len(welds), 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        mag = amplitude * rng.uniform(0.5, 1.5, len(welds))
        return cls(welds, d * mag[:, None], max(width, 1e-3))

    def field_enu(self, s: FloatArray) -> FloatArray:
        """Anomaly field (M, 3) in ENU, tesla, at chainages s (m); the two nearest welds."""
        s = np.asarray(s, dtype=np.float64).reshape(-1)
        out = np.zeros((len(s), 3))
        if len(self.welds) == 0:
            return out
        k = np.searchsorted(self.welds, s)
        for kk in (k - 1, k):
            valid = (kk >= 0) & (kk < len(self.welds))
            kc = np.clip(kk, 0, len(self.welds) - 1)
            g = np.exp(-0.5 * ((s - self.welds[kc]) / self.width) ** 2) * valid
            out += g[:, None] * self.vectors[kc]
        return out


def magnetometer_reading(
    c_nb: FloatArray,
    s: FloatArray,
    field_enu: FloatArray,
    attenuation: float,
    welds: WeldField,
    r_base_imu: FloatArray,
    hard_iron: FloatArray,
    noise: float,
    rng: np.random.Generator,
) -> FloatArray:
    """Magnetometer samples (M, 3) in imu_link, tesla.

    c_nb: (M, 3, 3) base_link -> ENU; s: (M,) chainage m; field_enu: (3,) Earth field T;
    attenuation: mu (dimensionless); r_base_imu: (3, 3) imu_link -> base_link; hard_iron: (3,)
    T in imu_link; noise: T one-sigma per axis.
    """
    b_n = attenuation * np.asarray(field_enu)[None, :] + welds.field_enu(s)
    b_b = np.einsum("mij,mi->mj", c_nb, b_n)
    b_i = b_b @ np.asarray(r_base_imu)  # rows: R_bi^T b
    b_i += np.asarray(hard_iron)[None, :]
    if noise > 0.0:
        b_i += rng.standard_normal(b_i.shape) * noise
    return b_i
