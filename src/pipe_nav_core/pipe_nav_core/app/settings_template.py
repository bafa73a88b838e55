"""The settings file of one pig (``pipe-nav config --template > pig.yaml``).

Lists what a user knows about their tool, each with its description and unit from
its config.SETTINGS entry and its default: the IMU noise model (a grade, or datasheet figures as
overrides), the IMU mounting, the odometer wheel, the pipe bore, the magnetometer and the marker
timing. ``pipe-nav smooth RUN.mcap --config pig.yaml`` reads it back (angles under ``*_deg``).
"""

from __future__ import annotations

import math

from pipe_nav_core.config import ANGLE_FIELDS, SETTINGS, NavConfig
from pipe_nav_core.model.sensors import GRADES

# NavConfig fields a user knows about the tool, in the order of the file
TOOL_FIELDS = (
    "mode",
    "imu_grade",
    "imu_mount_rpy",
    "odometer_lever_arm",
    "odometer_resolution",
    "pipe_diameter",
    "pipe_outer_diameter",
    "mag_update",
    "mag_declination",
    "mag_hard_iron",
    "marker_time_sigma",
    "heading_source",
)

# ImuSpec fields worth copying from a datasheet (SI units), shown commented out
DATASHEET = {
    "gyro_arw": "gyro angle random walk, rad/sqrt(s) (deg/sqrt(h) x pi / 180 / 60)",
    "gyro_bias_instability": "gyro bias instability, rad/s",
    "gyro_turn_on_bias": "gyro bias repeatability (turn-on to turn-on), rad/s",
    "accel_vrw": "accelerometer velocity random walk, m/s/sqrt(s)",
    "accel_bias_instability": "accelerometer bias instability, m/s^2",
    "accel_turn_on_bias": "accelerometer bias repeatability, m/s^2",
}


def yaml_value(value: object) -> str:
    """A setting's value as YAML (flow style for triples)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    if isinstance(value, float):
        return repr(round(value, 12))  # a degree value keeps no more than round-off noise
    return str(value)


def degrees_of(value: float | tuple[float, ...]) -> float | list[float]:
    """An angle setting (rad, or a tuple of them) in degrees, as the ``*_deg`` keys take it."""
    return [math.degrees(v) for v in value] if isinstance(value, tuple) else math.degrees(value)


def template_text() -> str:
    """The YAML text of the template: every TOOL_FIELDS setting at its default with its
    description, and the IMU datasheet overrides commented out with the industrial grade's
    figures as examples."""
    defaults = NavConfig()
    lines = [
        "# PipeNav settings of one pig: what you know about your tool.",
        "#   pipe-nav smooth RUN.mcap --config pig.yaml   (also replay and info)",
        "# SI units; angles in degrees where the key ends in _deg. Marker survey sigmas go with",
        "# the survey (the marker CSV's sigma_h_m, sigma_v_m), not here.",
    ]
    for name in TOOL_FIELDS:
        value = getattr(defaults, name)
        key = name
        if name in ANGLE_FIELDS:
            key, value = f"{name}_deg", degrees_of(value)
        lines += ["", f"# {SETTINGS[name].doc}", f"{key}: {yaml_value(value)}"]
        if name == "imu_grade":
            example = GRADES["industrial"]
            lines += [
                "# or the datasheet's figures, which replace the grade's (uncomment what you know;",
                "# the industrial grade's values shown):",
                "# imu_overrides:",
            ]
            lines += [
                f"#   {k}: {getattr(example, k):.6g}  # {doc}" for k, doc in DATASHEET.items()
            ]
    return "\n".join(lines) + "\n"
