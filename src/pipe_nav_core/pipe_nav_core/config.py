"""Estimator settings: one dataclass, validated, loadable from a flat dict (YAML, ROS parameters).

Fields are SI with radians. In dicts, any angle field may instead be given in degrees by
appending ``_deg`` to its name (``initial_azimuth_deg: 45``); that is how people write them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from .errors import ConfigError
from .sensors import GRADES, ImuSpec, imu_grade

NOISE_EPOCH_S = 0.1  # s, averaging time of odometer_speed_sigma and nhc_sigma

ANGLE_FIELDS = {
    "imu_mount_rpy",
    "initial_azimuth",
    "initial_heading_sigma",
    "initial_tilt_sigma",
    "boresight_sigma",
    "mag_declination",
    "mag_heading_sigma",
    "mag_dip_gate",
    "stop_gyro_threshold",
    "bend_min_angle",
}


# One line per NavConfig field with its unit, for people: the ROS parameter descriptions and
# ekf.yaml's comments, and the comments of `pipe-nav config --template`. Angles are described in
# degrees, as people give them (``<name>_deg``).
FIELD_DOCS: dict[str, str] = {
    "mode": "ins (strapdown INS aided by the odometer) or dr (odometer dead reckoning)",
    "imu_grade": "IMU noise model: auto (measured from the run) | consumer | industrial | tactical",
    "imu_mount_rpy": "roll, pitch, yaw of imu_link in base_link (imu_link->base_link), deg",
    "gyro_error_states": "estimate gyro scale factors and misalignments (9 more error states)",
    "accel_error_states": "estimate accelerometer scale factors and misalignments (9 more)",
    "filter_rate_hz": "covariance propagation and update rate, Hz",
    "reorder_window_s": "samples wait this long to be put in stamp order; later ones dropped, s",
    "odometer_speed_sigma": "odometer speed white noise averaged over 0.1 s, m/s",
    "nhc_sigma": "NHC: lateral and vertical body velocity noise averaged over 0.1 s, m/s",
    "odometer_resolution": "m per encoder count; 0 = the smallest step seen in the readings",
    "odometer_scale_sigma": "initial one-sigma odometer scale-factor error (fraction)",
    "odometer_scale_rw": "odometer scale-factor random walk, 1/sqrt(s)",
    "boresight_sigma": "initial one-sigma odometer/IMU misalignment, deg",
    "odometer_lever_arm": "wheel contact point in base_link, m",
    "pipe_diameter": "pipe diameter, m (wall-vs-centreline distance noise in bends)",
    "odometer_distance_sigma": "dr mode along-track distance noise, m/sqrt(m)",
    "dr_lateral_sigma": "dr mode lateral/vertical path noise, m/sqrt(m)",
    "stop_speed_threshold": "odometer speed below which the pig may be stopped, m/s",
    "stop_gyro_threshold": "|gyro| (bias removed) below which the pig may be stopped, deg/s",
    "zupt_sigma": "zero-velocity update noise, m/s",
    "zaru_sigma": "zero-angular-rate update noise, rad/s",
    "tilt_update": "gravity tilt update: auto (on in dr, off in ins) | on | off",
    "tilt_gate": "tilt update motion-test threshold on |C [0,0,g] x f|, m/s^2",
    "tilt_sigma": "tilt update noise, m/s^2",
    "mag_update": "use the magnetometer heading update",
    "mag_declination": "magnetic declination, east of true north positive, deg",
    "mag_attenuation": "in-pipe relative permeability mu; 0 = estimate at the start",
    "mag_heading_sigma": "magnetic heading noise, deg",
    "mag_magnitude_gate": "reject when | |m| / (mu |B|) - 1 | exceeds this",
    "mag_dip_gate": "reject when the dip angle differs more than this from the reference, deg",
    "mag_hard_iron": "magnetometer hard iron, T in imu_link (keep 0 if the driver corrects it)",
    "marker_time_sigma": "marker passage-time error, s",
    "static_alignment_s": "seconds of rest needed for the coarse alignment at the start, s",
    "heading_source": "initial heading from markers | magnetometer | fixed",
    "initial_azimuth": "initial azimuth for heading_source fixed, deg from north (with markers"
    " and fewer than two surveyed, the start value; the heading is reported unknown)",
    "initial_heading_sigma": "initial heading one-sigma before the second marker, deg",
    "initial_tilt_sigma": "initial roll/pitch one-sigma after static levelling, deg",
    "initial_position_sigma": "initial position one-sigma at the first marker, m",
    "gate_probability": "chi-square acceptance probability of every update, in (0.5, 1)",
    "pipe_outer_diameter": "pipe outer diameter for bending strain, m; 0 = pipe_diameter",
    "curvature_window": "chainage window of the curvature profile, m; 0 = 3 outer diameters",
    "bend_min_angle": "smallest bend listed (3-D angle between its end tangents), deg",
    "bend_threshold_radius": "a bend is where the radius of curvature is below this, m",
    "bend_class_limits": "bend class by radius, outer diameters: elbow < a <= induction < b"
    " <= field < c <= elastic",
    "strain_thresholds": "strain features: bending strain over these levels, percent",
}


AUTO_GRADE = "auto"  # imu_grade: the noise model measured from the run (imu_model)


@dataclass(frozen=True)
class NavConfig:
    """All settings of the navigation engine.

    mode: "ins" (strapdown INS aided by the odometer) or "dr" (odometer dead reckoning, seed 001).
    imu_grade: auto | consumer | industrial | tactical: the noise model used for process noise;
      ``imu_overrides`` replaces single ImuSpec fields (SI units, see sensors.ImuSpec). ``auto``
      (default): chosen from the run's own data by imu_model.choose before filtering; until
      then (and where nothing measures it) the industrial figures.
    imu_mount_rpy: (roll, pitch, yaw) rad of imu_link in base_link (rotation imu_link -> base_link,
      applied as Rz(yaw) Ry(pitch) Rx(roll)); zeros = aligned.
    filter_rate_hz: rate of covariance propagation and measurement updates (IMU integrates at its
      own rate in between).
    reorder_window_s: samples are held this long to put topics in stamp order; later ones are
      counted as late and dropped.
    """

    mode: str = "ins"
    imu_grade: str = "auto"
    imu_overrides: Mapping[str, float] = field(default_factory=dict)
    imu_mount_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_error_states: bool = True  # estimate gyro scale factors and misalignments (9 states)
    accel_error_states: bool = True  # the same for the accelerometers (9 states)
    filter_rate_hz: float = 10.0
    reorder_window_s: float = 0.5

    # Odometer (wheel on the pipe wall)
    # m/s, white noise of the speed averaged over NOISE_EPOCH_S (an epoch of T s: see over_epoch)
    odometer_speed_sigma: float = 0.005
    nhc_sigma: float = 0.005  # m/s, the same for the lateral and vertical body velocity (NHC)
    # m per count of the wheel encoder; 0 = the smallest step seen in the readings. The reading
    # errors at both ends of an epoch are states (quantization does not accumulate).
    odometer_resolution: float = 0.0
    odometer_scale_sigma: float = 0.02  # initial one-sigma of the scale-factor error (fraction)
    odometer_scale_rw: float = 1e-6  # 1/sqrt(s), random walk of the scale factor
    boresight_sigma: float = 0.01  # rad, initial one-sigma of odometer/IMU misalignment
    odometer_lever_arm: tuple[float, float, float] = (
        0.0,
        0.0,
        0.0,
    )  # m, wheel contact in base_link
    pipe_diameter: float = 0.2  # m; wall-vs-centreline distance noise in bends when no lever arm
    odometer_distance_sigma: float = 2e-3  # m/sqrt(m), DR-mode along-track distance noise
    dr_lateral_sigma: float = 1e-3  # m/sqrt(m), DR-mode lateral/vertical path noise

    # Stops: zero velocity and zero angular rate
    stop_speed_threshold: float = 0.002  # m/s, odometer speed below which the pig may be stopped
    stop_gyro_threshold: float = 0.02  # rad/s, |gyro| (bias removed) below which it may be stopped
    zupt_sigma: float = 0.002  # m/s
    zaru_sigma: float = 1e-4  # rad/s, extra noise of the zero-angular-rate update

    # Gravity tilt (seed 001 eq. 11-13)
    tilt_update: str = "auto"  # auto (on in dr mode, off in ins mode) | on | off
    tilt_gate: float = 0.05  # m/s^2, seed 001 eq. 13 threshold xi_g on |C [0,0,g] x f|
    tilt_sigma: float = 0.02  # m/s^2

    # Magnetometer (seed 001 eq. 10, 31)
    mag_update: bool = False
    mag_declination: float = 0.0  # rad, east of true north positive
    mag_attenuation: float = 0.0  # in-pipe relative permeability mu; 0 = estimate at the start
    mag_heading_sigma: float = 0.05  # rad
    mag_magnitude_gate: float = 0.15  # reject when | |m| / (mu |B|) - 1 | exceeds this
    mag_dip_gate: float = 0.2  # rad, reject when the dip angle differs more from the reference
    mag_hard_iron: tuple[float, float, float] = (0.0, 0.0, 0.0)  # T, in imu_link

    # Markers
    marker_time_sigma: float = 0.03  # s, passage-time error; adds speed * sigma along track

    # Alignment and initial uncertainty
    static_alignment_s: float = 2.0  # s of rest needed for coarse alignment at the start
    heading_source: str = "markers"  # markers | magnetometer | fixed
    # rad, used with heading_source "fixed"; with "markers" and fewer than two surveyed markers
    # the live filter starts on it and reports the heading unknown until the second marker
    initial_azimuth: float = 0.0
    initial_heading_sigma: float = math.radians(20.0)  # rad, before the second marker
    initial_tilt_sigma: float = math.radians(0.5)  # rad, after static levelling
    initial_position_sigma: float = 0.05  # m, when starting at the first marker

    # Innovation gating
    gate_probability: float = 0.9999  # chi-square acceptance probability of every update

    # Integrity products, computed from the smoothed solution (products/)
    pipe_outer_diameter: float = 0.0  # m, for bending strain; 0 = pipe_diameter
    curvature_window: float = 0.0  # m of chainage; 0 = 3 outer diameters, at least 0.5 m
    bend_min_angle: float = math.radians(1.0)  # rad, 3-D angle between a bend's end tangents
    bend_threshold_radius: float = 2000.0  # m: curvature over 1/this is part of a bend
    bend_class_limits: tuple[float, float, float] = (2.5, 12.0, 150.0)  # outer diameters
    strain_thresholds: tuple[float, ...] = (0.125, 0.2)  # percent bending strain

    def over_epoch(self, sigma: float, epoch_s: float) -> float:
        """Sigma of a white velocity noise averaged over epoch_s (s), given its sigma over
        NOISE_EPOCH_S: sigma * sqrt(NOISE_EPOCH_S / epoch_s), so that the information the
        odometer and the NHC carry per second does not depend on the epoch length (epochs cut
        short at marker passages, other filter rates)."""
        return sigma * math.sqrt(NOISE_EPOCH_S / max(epoch_s, 1e-3))

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
        known = {f.name: f for f in fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in values.items():
            name = key
            if key.endswith("_deg") and key[:-4] in ANGLE_FIELDS:
                name = key[:-4]
                value = _to_rad(value, key)
            if name not in known:
                raise ConfigError(f"unknown setting {key!r}")
            kwargs[name] = tuple(value) if isinstance(value, list) else value
        cfg = cls(**kwargs)
        cfg.validate()
        return cfg

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid setting."""
        if self.mode not in ("ins", "dr"):
            raise ConfigError(f"mode must be 'ins' or 'dr', not {self.mode!r}")
        if self.imu_grade != AUTO_GRADE and self.imu_grade not in GRADES:
            raise ConfigError(
                f"imu_grade must be auto, {', '.join(sorted(GRADES))}, not {self.imu_grade!r}"
            )
        try:
            self.imu_spec()
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"imu_grade/imu_overrides: {exc}") from None
        if self.tilt_update not in ("auto", "on", "off"):
            raise ConfigError(f"tilt_update must be auto, on or off, not {self.tilt_update!r}")
        if self.heading_source not in ("markers", "magnetometer", "fixed"):
            raise ConfigError(
                f"heading_source must be markers, magnetometer or fixed, "
                f"not {self.heading_source!r}"
            )
        for name in ("imu_mount_rpy", "odometer_lever_arm", "mag_hard_iron"):
            v = getattr(self, name)
            if len(v) != 3 or not all(math.isfinite(float(x)) for x in v):
                raise ConfigError(f"{name} must be three finite numbers, not {v!r}")
        positive = (
            "filter_rate_hz",
            "odometer_speed_sigma",
            "nhc_sigma",
            "odometer_scale_sigma",
            "boresight_sigma",
            "pipe_diameter",
            "odometer_distance_sigma",
            "dr_lateral_sigma",
            "zupt_sigma",
            "zaru_sigma",
            "tilt_gate",
            "tilt_sigma",
            "mag_heading_sigma",
            "mag_magnitude_gate",
            "mag_dip_gate",
            "static_alignment_s",
            "initial_heading_sigma",
            "initial_tilt_sigma",
            "initial_position_sigma",
            "bend_min_angle",
            "bend_threshold_radius",
        )
        for name in positive:
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(f"{name} must be a positive number, not {v!r}")
        non_negative = (
            "reorder_window_s",
            "odometer_resolution",
            "odometer_scale_rw",
            "stop_speed_threshold",
            "stop_gyro_threshold",
            "mag_attenuation",
            "marker_time_sigma",
            "pipe_outer_diameter",
            "curvature_window",
        )
        for name in non_negative:
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"{name} must be a number >= 0, not {v!r}")
        for name, count in (("bend_class_limits", 3), ("strain_thresholds", 0)):
            v = getattr(self, name)
            try:
                ok = all(math.isfinite(float(x)) and float(x) > 0 for x in v) and list(v) == sorted(
                    v
                )
            except (TypeError, ValueError):
                ok = False
            if not ok or (count and len(v) != count) or not v:
                what = f"{count} " if count else ""
                raise ConfigError(
                    f"{name} must be {what}positive numbers in increasing order, not {v!r}"
                )
        if not 0.5 < self.gate_probability < 1.0:
            raise ConfigError(f"gate_probability must be in (0.5, 1), not {self.gate_probability}")
        if self.filter_rate_hz > 1000:
            raise ConfigError("filter_rate_hz must be at most 1000")


def _to_rad(value: Any, key: str) -> Any:
    try:
        if isinstance(value, (list, tuple)):
            return tuple(math.radians(float(v)) for v in value)
        return math.radians(float(value))
    except (TypeError, ValueError):
        raise ConfigError(f"{key} must be a number (degrees), not {value!r}") from None
