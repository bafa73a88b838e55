"""Sensor error specifications, in one place, shared by the simulator and the filter's noise model.

All fields are SI: rad, rad/s, m/s, m/s^2, s. Helper constructors convert the data-sheet units
people use (deg/sqrt(h), deg/h, mg, ppm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

DEG = math.pi / 180.0
HOUR = 3600.0
G0 = 9.80665  # m/s^2, standard gravity (for mg and ug units only)


def deg_per_sqrt_h(x: float) -> float:
    """Angle random walk deg/sqrt(h) -> rad/sqrt(s)."""
    return x * DEG / math.sqrt(HOUR)


def deg_per_h(x: float) -> float:
    """deg/h -> rad/s."""
    return x * DEG / HOUR


def mps_per_sqrt_h(x: float) -> float:
    """Velocity random walk m/s/sqrt(h) -> m/s/sqrt(s)."""
    return x / math.sqrt(HOUR)


def milli_g(x: float) -> float:
    """mg -> m/s^2."""
    return x * 1e-3 * G0


@dataclass(frozen=True)
class ImuSpec:
    """Error model of one IMU grade (one-sigma values, per axis).

    Gyro: arw rad/sqrt(s); bias_instability rad/s (first-order Gauss-Markov sigma) with
    corr_time s; turn_on_bias rad/s (random constant per run); scale_factor (fraction);
    misalignment rad; quantization rad (angle quantum, 0 for none).
    Accelerometer: the same with m/s/sqrt(s), m/s^2 and m/s.
    """

    name: str
    gyro_arw: float
    gyro_bias_instability: float
    gyro_bias_corr_time: float
    gyro_turn_on_bias: float
    gyro_scale_factor: float
    gyro_misalignment: float
    gyro_quantization: float
    accel_vrw: float
    accel_bias_instability: float
    accel_bias_corr_time: float
    accel_turn_on_bias: float
    accel_scale_factor: float
    accel_misalignment: float
    accel_quantization: float

    def scaled(self, factor: float) -> ImuSpec:
        """The same IMU with every stochastic error multiplied by factor (0 = error-free)."""
        return replace(
            self,
            gyro_arw=self.gyro_arw * factor,
            gyro_bias_instability=self.gyro_bias_instability * factor,
            gyro_turn_on_bias=self.gyro_turn_on_bias * factor,
            gyro_scale_factor=self.gyro_scale_factor * factor,
            gyro_misalignment=self.gyro_misalignment * factor,
            gyro_quantization=self.gyro_quantization * factor,
            accel_vrw=self.accel_vrw * factor,
            accel_bias_instability=self.accel_bias_instability * factor,
            accel_turn_on_bias=self.accel_turn_on_bias * factor,
            accel_scale_factor=self.accel_scale_factor * factor,
            accel_misalignment=self.accel_misalignment * factor,
            accel_quantization=self.accel_quantization * factor,
        )


# Consumer MEMS (MPU-9250 class; seed 001 table 1: gyro bias stability 0.007 deg/s, accel 0.2 mg).
CONSUMER = ImuSpec(
    name="consumer",
    gyro_arw=deg_per_sqrt_h(0.6),
    gyro_bias_instability=0.007 * DEG,
    gyro_bias_corr_time=300.0,
    gyro_turn_on_bias=0.5 * DEG,
    gyro_scale_factor=0.01,
    gyro_misalignment=1e-3,
    gyro_quantization=0.0,
    accel_vrw=mps_per_sqrt_h(0.2),
    accel_bias_instability=milli_g(0.2),
    accel_bias_corr_time=300.0,
    accel_turn_on_bias=milli_g(20.0),
    accel_scale_factor=0.01,
    accel_misalignment=1e-3,
    accel_quantization=0.0,
)

# Industrial MEMS (ADIS16490 class).
INDUSTRIAL = ImuSpec(
    name="industrial",
    gyro_arw=deg_per_sqrt_h(0.09),
    gyro_bias_instability=deg_per_h(1.8),
    gyro_bias_corr_time=600.0,
    gyro_turn_on_bias=deg_per_h(25.0),
    gyro_scale_factor=1e-3,
    gyro_misalignment=3e-4,
    gyro_quantization=0.0,
    accel_vrw=mps_per_sqrt_h(0.008),
    accel_bias_instability=milli_g(0.0036),
    accel_bias_corr_time=600.0,
    accel_turn_on_bias=milli_g(3.0),
    accel_scale_factor=5e-4,
    accel_misalignment=3e-4,
    accel_quantization=0.0,
)

# Tactical MEMS (Honeywell HG4930 class, seed 003).
TACTICAL = ImuSpec(
    name="tactical",
    gyro_arw=deg_per_sqrt_h(0.04),
    gyro_bias_instability=deg_per_h(0.25),
    gyro_bias_corr_time=1000.0,
    gyro_turn_on_bias=deg_per_h(7.0),
    gyro_scale_factor=5e-4,
    gyro_misalignment=1e-4,
    gyro_quantization=0.0,
    accel_vrw=mps_per_sqrt_h(0.03),
    accel_bias_instability=milli_g(0.025),
    accel_bias_corr_time=1000.0,
    accel_turn_on_bias=milli_g(1.7),
    accel_scale_factor=3e-4,
    accel_misalignment=1e-4,
    accel_quantization=0.0,
)

GRADES: dict[str, ImuSpec] = {s.name: s for s in (CONSUMER, INDUSTRIAL, TACTICAL)}


def imu_grade(name: str) -> ImuSpec:
    """The ImuSpec of a named grade (consumer, industrial, tactical)."""
    try:
        return GRADES[name]
    except KeyError:
        raise ValueError(f"unknown IMU grade {name!r}; choose one of {sorted(GRADES)}") from None
