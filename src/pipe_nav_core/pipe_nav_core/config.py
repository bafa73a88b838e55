"""Estimator settings: one dataclass, validated, loadable from a flat dict (YAML, ROS parameters).

Fields are SI with radians. In dicts, any angle field may instead be given in degrees by
appending ``_deg`` to its name (``initial_azimuth_deg: 45``); that is how people write them.

Each field carries its :class:`Setting` as dataclass metadata (``SETTINGS[name]``): a one-line
description with the unit, the :class:`Rule` its values obey, and whether it is an angle.
validate(), ANGLE_FIELDS, ``pipe-nav config --template`` and the ROS parameters (their
descriptions and ranges, config/ekf.yaml: pipe_nav_ros.params) are all made from it.

About 430 lines, one module on purpose: every setting is declared here once with its doc, unit
and rule (:class:`Setting`), and validation, the template, the ROS parameters and ekf.yaml are
all built from that one table.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from pipe_nav_core.errors import ConfigError
from pipe_nav_core.model.sensors import GRADES, ImuSpec, imu_grade

# Hz: the smoothing passes' epoch rate with a tactical IMU (NavConfig.smoothing_rate_hz). The
# 10 km line's figures are those of 10 Hz epochs (1:10640 against 1:10649, graph 1:10692 against
# 1:10662) at 2.5 times the speed; an industrial IMU loses 2 mm on the sag pipe with exact
# surveys at this rate, and a consumer one diverges on the test pipes (BENCHMARKS.md).
LONG_EPOCH_HZ = 2.5
NOISE_EPOCH_S = 0.1  # s, averaging time of odometer_speed_sigma and nhc_sigma
AUTO_GRADE = "auto"  # imu_grade: the noise model measured from the run (imu_model)


def _number(value: Any) -> bool:
    """A finite int or float (a bool counts as an int, as in Python)."""
    return isinstance(value, (int, float)) and math.isfinite(value)


class Rule:
    """The values a setting takes: ``problem`` is validate()'s message for an invalid value
    (None: valid); ``bounds`` the closed interval, SI units, holding every valid value of a
    number setting (None: no such interval), declared as the ROS parameter's range."""

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        return None

    def bounds(self) -> tuple[float, float] | None:
        return None


class Flag(Rule):
    """true or false; not checked, so that ``--set mag_update=1`` (an int) works."""


class Finite(Rule):
    """Any finite number."""

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        return None if _number(value) else f"{name} must be a finite number, not {value!r}"


@dataclass(frozen=True)
class Positive(Rule):
    """A finite number > 0 and <= at_most."""

    at_most: float = math.inf

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        if not _number(value) or value <= 0:
            return f"{name} must be a positive number, not {value!r}"
        if value > self.at_most:
            return f"{name} must be at most {self.at_most}"
        return None

    def bounds(self) -> tuple[float, float] | None:
        return (0.0, float(self.at_most))


class NonNegative(Rule):
    """A finite number >= 0 (0 often means: work it out)."""

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        if _number(value) and value >= 0:
            return None
        return f"{name} must be a number >= 0, not {value!r}"

    def bounds(self) -> tuple[float, float] | None:
        return (0.0, math.inf)


@dataclass(frozen=True)
class Between(Rule):
    """A number in the open interval (low, high)."""

    low: float
    high: float

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        if _number(value) and self.low < value < self.high:
            return None
        return f"{name} must be in ({self.low}, {self.high}), not {value}"

    def bounds(self) -> tuple[float, float] | None:
        return (float(self.low), float(self.high))


@dataclass(frozen=True)
class OneOf(Rule):
    """One of the choices; the message lists them (quoted or not) with ``last`` before the last."""

    choices: tuple[str, ...]
    quote: bool = False
    last: str = " or "

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        if value in self.choices:
            return None
        said = [repr(c) if self.quote else c for c in self.choices]
        return f"{name} must be {', '.join(said[:-1])}{self.last}{said[-1]}, not {value!r}"


class Triple(Rule):
    """Three finite numbers: a vector, or roll, pitch, yaw."""

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        try:
            ok = len(value) == 3 and all(math.isfinite(float(x)) for x in value)
        except (TypeError, ValueError):
            ok = False
        return None if ok else f"{name} must be three finite numbers, not {value!r}"


@dataclass(frozen=True)
class Increasing(Rule):
    """At least one positive number, none smaller than the one before; ``count`` of them
    (0 = any count)."""

    count: int = 0

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        try:
            ok = all(math.isfinite(float(x)) and float(x) > 0 for x in value)
            ok = ok and list(value) == sorted(value)
        except (TypeError, ValueError):
            ok = False
        if ok and value and (not self.count or len(value) == self.count):
            return None
        what = f"{self.count} " if self.count else ""
        return f"{name} must be {what}positive numbers in increasing order, not {value!r}"


class ImuOverrides(Rule):
    """ImuSpec fields replacing the grade's figures: checked together with imu_grade (which
    comes before it), by building the model (NavConfig.imu_spec)."""

    def problem(self, name: str, value: Any, config: NavConfig) -> str | None:
        try:
            config.imu_spec()
        except (ValueError, TypeError) as exc:
            return f"imu_grade/imu_overrides: {exc}"
        return None


FLAG, FINITE, POSITIVE, NON_NEGATIVE, TRIPLE = Flag(), Finite(), Positive(), NonNegative(), Triple()


@dataclass(frozen=True)
class Setting:
    """One NavConfig field described for people and for checks.

    doc: one line with the unit, for the ROS parameter descriptions, ekf.yaml's comments and
      ``pipe-nav config --template``; an angle's unit there is degrees, as people give it.
    rule: the values it takes (validate()'s check and message, the ROS parameter's range).
    angle: radians in NavConfig, given in degrees under ``<name>_deg``.
    """

    doc: str
    rule: Rule
    angle: bool = False


def _field(default: Any, rule: Rule, doc: str, angle: bool = False) -> Any:
    """A NavConfig field with its Setting as metadata (a dict default is made per instance)."""
    meta = {"setting": Setting(doc, rule, angle)}
    if isinstance(default, dict):
        return field(default_factory=dict, metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class NavConfig:
    """All settings of the navigation engine; each field's description, unit and rule are its
    :class:`Setting` (``SETTINGS``).

    imu_grade ``auto`` chooses the noise model from the run's own data (imu_model.choose) before
    filtering; until then, and where nothing measures it, the industrial figures.
    ``imu_overrides`` replaces single ImuSpec fields (SI units, see sensors.ImuSpec).
    imu_mount_rpy is the rotation imu_link -> base_link, applied as Rz(yaw) Ry(pitch) Rx(roll).
    The IMU integrates at its own rate between the filter_rate_hz epochs.
    """

    mode: str = _field(
        "ins",
        OneOf(("ins", "dr"), quote=True),
        "ins (strapdown INS aided by the odometer) or dr (odometer dead reckoning)",
    )
    imu_grade: str = _field(
        AUTO_GRADE,
        OneOf((AUTO_GRADE, *sorted(GRADES)), last=", "),
        "IMU noise model: auto (measured from the run) | consumer | industrial | tactical",
    )
    imu_overrides: Mapping[str, float] = _field(
        {}, ImuOverrides(), "ImuSpec fields replacing the grade's, SI units"
    )
    imu_mount_rpy: tuple[float, float, float] = _field(
        (0.0, 0.0, 0.0),
        TRIPLE,
        "roll, pitch, yaw of imu_link in base_link (imu_link->base_link), deg",
        angle=True,
    )
    gyro_error_states: bool = _field(
        True, FLAG, "estimate gyro scale factors and misalignments (9 more error states)"
    )
    accel_error_states: bool = _field(
        True, FLAG, "estimate accelerometer scale factors and misalignments (9 more)"
    )
    filter_rate_hz: float = _field(
        10.0, Positive(at_most=1000), "covariance propagation and update rate, Hz"
    )
    smoother_rate_hz: float = _field(
        0.0,
        NON_NEGATIVE,
        "epoch rate of the rts and graph smoothing passes, Hz; 0 = auto: 2.5 in ins mode with "
        "an IMU of tactical grade or better, else filter_rate_hz",
    )
    reorder_window_s: float = _field(
        0.5, NON_NEGATIVE, "samples wait this long to be put in stamp order; later ones dropped, s"
    )

    # Odometer (wheel on the pipe wall). Speed noises are over NOISE_EPOCH_S (see over_epoch).
    odometer_speed_sigma: float = _field(
        0.005, POSITIVE, "odometer speed white noise averaged over 0.1 s, m/s"
    )
    nhc_sigma: float = _field(
        0.005, POSITIVE, "NHC: lateral and vertical body velocity noise averaged over 0.1 s, m/s"
    )
    # The reading errors at both ends of an epoch are states (quantization does not accumulate).
    odometer_resolution: float = _field(
        0.0, NON_NEGATIVE, "m per encoder count; 0 = the smallest step seen in the readings"
    )
    odometer_scale_sigma: float = _field(
        0.02, POSITIVE, "initial one-sigma odometer scale-factor error (fraction)"
    )
    odometer_scale_rw: float = _field(
        1e-6, NON_NEGATIVE, "odometer scale-factor random walk, 1/sqrt(s)"
    )
    boresight_sigma: float = _field(
        0.01, POSITIVE, "initial one-sigma odometer/IMU misalignment, deg", angle=True
    )
    odometer_lever_arm: tuple[float, float, float] = _field(
        (0.0, 0.0, 0.0), TRIPLE, "wheel contact point in base_link, m"
    )
    pipe_diameter: float = _field(
        0.2, POSITIVE, "pipe diameter, m (wall-vs-centreline distance noise in bends)"
    )
    odometer_distance_sigma: float = _field(
        2e-3, POSITIVE, "dr mode along-track distance noise, m/sqrt(m)"
    )
    dr_lateral_sigma: float = _field(
        1e-3, POSITIVE, "dr mode lateral/vertical path noise, m/sqrt(m)"
    )

    # Stops: zero velocity and zero angular rate
    stop_speed_threshold: float = _field(
        0.002, NON_NEGATIVE, "odometer speed below which the pig may be stopped, m/s"
    )
    stop_gyro_threshold: float = _field(
        0.02,
        NON_NEGATIVE,
        "|gyro| (bias removed) below which the pig may be stopped, deg/s",
        angle=True,
    )
    zupt_sigma: float = _field(0.002, POSITIVE, "zero-velocity update noise, m/s")
    zaru_sigma: float = _field(1e-4, POSITIVE, "zero-angular-rate update noise, rad/s")

    # Straight pipe between bends (smoothing passes about a reference only)
    straight_pipe_sigma: float = _field(
        1e-3,
        NON_NEGATIVE,
        "straight-pipe update noise (the path's turn rate outside bends), rad/s; 0 = off",
    )
    straight_pipe_curvature: float = _field(
        1e-3, POSITIVE, "largest curvature of the previous pass's path taken as straight, 1/m"
    )
    straight_pipe_margin: float = _field(
        1.5, NON_NEGATIVE, "length of pipe left out at each end of a bend, m"
    )
    straight_pipe_wander: float = _field(
        3e-4,
        NON_NEGATIVE,
        "how far a straight section's direction may turn, deg per sqrt(m) of pipe; 0 = no "
        "section direction state (nor with a gyro whose angle random walk is under a tenth of "
        "it per sqrt(s) at 1 m/s)",
        angle=True,
    )

    # Gravity tilt (seed 001 eq. 11-13; tilt_gate is eq. 13's threshold xi_g)
    tilt_update: str = _field(
        "auto",
        OneOf(("auto", "on", "off")),
        "gravity tilt update: auto (on in dr, off in ins) | on | off",
    )
    tilt_gate: float = _field(
        0.05, POSITIVE, "tilt update motion-test threshold on |C [0,0,g] x f|, m/s^2"
    )
    tilt_sigma: float = _field(0.02, POSITIVE, "tilt update noise, m/s^2")

    # Magnetometer (seed 001 eq. 10, 31)
    mag_update: bool = _field(False, FLAG, "use the magnetometer heading update")
    mag_declination: float = _field(
        0.0, FINITE, "magnetic declination, east of true north positive, deg", angle=True
    )
    mag_attenuation: float = _field(
        0.0, NON_NEGATIVE, "in-pipe relative permeability mu; 0 = estimate at the start"
    )
    mag_heading_sigma: float = _field(0.05, POSITIVE, "magnetic heading noise, deg", angle=True)
    mag_magnitude_gate: float = _field(
        0.15, POSITIVE, "reject when | |m| / (mu |B|) - 1 | exceeds this"
    )
    mag_dip_gate: float = _field(
        0.2,
        POSITIVE,
        "reject when the dip angle differs more than this from the reference, deg",
        angle=True,
    )
    mag_hard_iron: tuple[float, float, float] = _field(
        (0.0, 0.0, 0.0),
        TRIPLE,
        "magnetometer hard iron, T in imu_link (keep 0 if the driver corrects it)",
    )

    # Markers (the passage-time error adds speed * sigma along track)
    marker_time_sigma: float = _field(0.03, NON_NEGATIVE, "marker passage-time error, s")

    # Alignment and initial uncertainty
    static_alignment_s: float = _field(
        2.0, POSITIVE, "seconds of rest needed for the coarse alignment at the start, s"
    )
    heading_source: str = _field(
        "markers",
        OneOf(("markers", "magnetometer", "fixed")),
        "initial heading from markers | magnetometer | fixed",
    )
    initial_azimuth: float = _field(
        0.0,
        FINITE,
        "initial azimuth for heading_source fixed, deg from north (with markers"
        " and fewer than two surveyed, the start value; the heading is reported unknown)",
        angle=True,
    )
    initial_heading_sigma: float = _field(
        math.radians(20.0),
        POSITIVE,
        "initial heading one-sigma before the second marker, deg",
        angle=True,
    )
    initial_tilt_sigma: float = _field(
        math.radians(0.5),
        POSITIVE,
        "initial roll/pitch one-sigma after static levelling, deg",
        angle=True,
    )
    initial_position_sigma: float = _field(
        0.05, POSITIVE, "initial position one-sigma at the first marker, m"
    )

    # Innovation gating
    gate_probability: float = _field(
        0.9999, Between(0.5, 1), "chi-square acceptance probability of every update, in (0.5, 1)"
    )

    # Integrity products, computed from the smoothed solution (products/)
    pipe_outer_diameter: float = _field(
        0.0, NON_NEGATIVE, "pipe outer diameter for bending strain, m; 0 = pipe_diameter"
    )
    curvature_window: float = _field(  # at least 0.5 m when derived
        0.0, NON_NEGATIVE, "chainage window of the curvature profile, m; 0 = 3 outer diameters"
    )
    bend_min_angle: float = _field(
        math.radians(1.0),
        POSITIVE,
        "smallest bend listed (3-D angle between its end tangents), deg",
        angle=True,
    )
    bend_threshold_radius: float = _field(
        2000.0, POSITIVE, "a bend is where the radius of curvature is below this, m"
    )
    bend_class_limits: tuple[float, float, float] = _field(
        (2.5, 12.0, 150.0),
        Increasing(3),
        "bend class by radius, outer diameters: elbow < a <= induction < b <= field < c <= elastic",
    )
    strain_thresholds: tuple[float, ...] = _field(
        (0.125, 0.2), Increasing(), "strain features: bending strain over these levels, percent"
    )

    def over_epoch(self, sigma: float, epoch_s: float) -> float:
        """Sigma of a white velocity noise averaged over epoch_s (s), given its sigma over
        NOISE_EPOCH_S: sigma * sqrt(NOISE_EPOCH_S / epoch_s), so that the information the
        odometer and the NHC carry per second does not depend on the epoch length (epochs cut
        short at marker passages, other filter rates)."""
        return sigma * math.sqrt(NOISE_EPOCH_S / max(epoch_s, 1e-3))

    def smoothing_rate_hz(self) -> float:
        """The epoch rate of the rts and graph smoothing passes (smooth.passes), Hz:
        smoother_rate_hz, or when 0 (auto) LONG_EPOCH_HZ in INS mode where the IMU
        (:meth:`imu_spec`) is at least as stable as a tactical one (gyro turn-on bias and
        scale factor, accelerometer turn-on bias), else filter_rate_hz. An epoch's odometer and
        NHC updates constrain its mean body velocity through the attitude at its end, and its
        covariance is propagated to first order: over a long epoch that linearization holds
        only while the IMU's errors grow slowly."""
        if self.smoother_rate_hz:
            return self.smoother_rate_hz
        imu, steady = self.imu_spec(), imu_grade("tactical")
        if (
            self.mode == "ins"
            and imu.gyro_turn_on_bias <= steady.gyro_turn_on_bias
            and imu.gyro_scale_factor <= steady.gyro_scale_factor
            and imu.accel_turn_on_bias <= steady.accel_turn_on_bias
        ):
            return min(self.filter_rate_hz, LONG_EPOCH_HZ)
        return self.filter_rate_hz

    def imu_spec(self) -> ImuSpec:
        """The process-noise IMU model: the named grade with overrides applied."""
        spec = imu_grade("industrial" if self.imu_grade == AUTO_GRADE else self.imu_grade)
        return replace(spec, **dict(self.imu_overrides)) if self.imu_overrides else spec

    def outer_diameter(self) -> float:
        """The pipe's outer diameter for strain, m (pipe_diameter when not given)."""
        return self.pipe_outer_diameter or self.pipe_diameter

    def window(self) -> float:
        """The curvature window, m of chainage (default 3 outer diameters, at least 0.5 m)."""
        return self.curvature_window or max(3.0 * self.outer_diameter(), 0.5)

    def tilt_enabled(self) -> bool:
        return self.tilt_update == "on" or (self.tilt_update == "auto" and self.mode == "dr")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> NavConfig:
        """Build and validate from a flat mapping; ``*_deg`` keys are converted to radians."""
        kwargs: dict[str, Any] = {}
        for key, value in values.items():
            name = key
            if key.endswith("_deg") and key[:-4] in ANGLE_FIELDS:
                name = key[:-4]
                value = _to_rad(value, key)
            if name not in SETTINGS:
                raise ConfigError(f"unknown setting {key!r}")
            kwargs[name] = tuple(value) if isinstance(value, list) else value
        cfg = cls(**kwargs)
        cfg.validate()
        return cfg

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def validate(self) -> None:
        """Raise ConfigError with the message of the first field, in field order, whose value
        its Setting's rule refuses."""
        for name, setting in SETTINGS.items():
            problem = setting.rule.problem(name, getattr(self, name), self)
            if problem:
                raise ConfigError(problem)


# Every field's Setting, in field order, and the angle fields (radians here, ``<name>_deg`` for
# people).
SETTINGS: dict[str, Setting] = {f.name: f.metadata["setting"] for f in fields(NavConfig)}
ANGLE_FIELDS = frozenset(name for name, setting in SETTINGS.items() if setting.angle)


def _to_rad(value: Any, key: str) -> Any:
    try:
        if isinstance(value, (list, tuple)):
            return tuple(math.radians(float(v)) for v in value)
        return math.radians(float(value))
    except (TypeError, ValueError):
        raise ConfigError(f"{key} must be a number (degrees), not {value!r}") from None
