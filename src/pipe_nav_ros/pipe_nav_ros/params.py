"""ROS parameters of the PipeNav nodes, without rclpy: names, defaults, types, validation.

Every node declares its parameters from the specs here (``ros_common.declare``) and builds its
settings from their values with the functions here, so a wrong value is refused with the same
clear :class:`~pipe_nav_core.config.ConfigError` in the node and in the unit tests.

Estimator settings: one ROS parameter per :class:`~pipe_nav_core.config.NavConfig` field, with
the field's default, and its description and range from the field's
:class:`~pipe_nav_core.config.Setting`. Angle fields are given in degrees under ``<field>_deg``
(as in ``config/ekf.yaml``); triples are double arrays; ``imu_overrides`` becomes one optional
parameter per :class:`~pipe_nav_core.model.sensors.ImuSpec` number, ``imu_overrides.<field>`` (SI
units, unset = the grade's value). Integers are accepted where a double is expected (``10`` for
``10.0``).

Over 400 lines: the parameters of all five nodes, their checks and the parameter files written
from them (config/*.yaml) are one table and its uses, kept together.
"""

from __future__ import annotations

import io
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

from pipe_nav_core import ANGLE_FIELDS, SETTINGS, ConfigError, ImuSpec, NavConfig, Setting

# kinds of parameter value
FLOAT, INT, BOOL, STR, FLOATS = "float", "int", "bool", "str", "floats"


@dataclass(frozen=True)
class ParamSpec:
    """One ROS parameter: name, default (None = optional, unset), kind, description.

    ``length`` fixes the number of elements of a FLOATS parameter (0 = any). ``range`` is the
    inclusive (from, to) a FLOAT parameter is declared with (rclpy refuses a double outside it;
    the checks here stay the rule), None = none.
    """

    name: str
    default: Any
    kind: str
    description: str = ""
    length: int = 0
    range: tuple[float, float] | None = None

    def coerce(self, value: Any) -> Any:
        """The value converted to the Python type of this parameter; ConfigError if impossible."""
        name = self.name
        if self.kind == BOOL:
            if isinstance(value, bool):
                return value
            raise ConfigError(f"{name} must be true or false, not {value!r}")
        if self.kind == STR:
            if isinstance(value, str):
                return value
            raise ConfigError(f"{name} must be a string, not {value!r}")
        if self.kind == INT:
            if isinstance(value, int) and not isinstance(value, bool):
                return int(value)
            raise ConfigError(f"{name} must be an integer, not {value!r}")
        if self.kind == FLOAT:
            return _finite(name, value)
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
            try:  # numpy arrays and array.array from rclpy
                value = list(value)
            except TypeError:
                raise ConfigError(f"{name} must be a list of numbers, not {value!r}") from None
        out = tuple(_finite(name, v) for v in value)
        if self.length and len(out) != self.length:
            raise ConfigError(f"{name} must have {self.length} numbers, not {len(out)}: {value!r}")
        return out


def _finite(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        try:
            import numpy as np

            if isinstance(value, np.number) and not isinstance(value, np.bool_):
                value = float(value)
            else:
                raise TypeError
        except TypeError:
            raise ConfigError(f"{name} must be a number, not {value!r}") from None
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{name} must be a finite number, not {value!r}")
    return v


def values_from(specs: Sequence[ParamSpec], values: Mapping[str, Any]) -> dict[str, Any]:
    """Coerce the given values (missing or None: the default) of the specs to Python types."""
    out: dict[str, Any] = {}
    for spec in specs:
        raw = values.get(spec.name)
        if raw is None:
            out[spec.name] = spec.default
        else:
            out[spec.name] = spec.coerce(raw)
    return out


# --------------------------------------------------------------------------------------------
# Estimator settings (NavConfig)


IMU_OVERRIDES_PREFIX = "imu_overrides."


def _ros_default(value: Any, in_degrees: bool, digits: int | None = 12) -> Any:
    """A NavConfig value as a ROS parameter value: tuples as lists of floats, angles in degrees
    (rounded to ``digits`` decimals for people, None = exact)."""
    if isinstance(value, tuple):
        return [_ros_default(float(v), in_degrees, digits) for v in value]
    if in_degrees:
        deg = math.degrees(value)
        return deg if digits is None else round(deg, digits)
    return value


def _ros_range(setting: Setting) -> tuple[float, float] | None:
    """The bounds of a setting's rule as a ROS parameter range (degrees for an angle), or None.

    The range is inclusive, so an edge the rule excludes (0 of a positive setting) passes it
    and is refused by the validation; an infinite bound is given as the largest double, as
    rqt_reconfigure cannot show a parameter with an infinite limit.
    """
    bounds = setting.rule.bounds()
    if bounds is None:
        return None
    low, high = (math.degrees(b) if setting.angle else b for b in bounds)
    return max(low, -sys.float_info.max), min(high, sys.float_info.max)


def nav_param_specs() -> list[ParamSpec]:
    """One spec per NavConfig field (angles as ``<name>_deg``) and per ImuSpec override; the
    description and range come from the field's Setting."""
    specs: list[ParamSpec] = []
    for name, default in NavConfig().to_dict().items():
        if name == "imu_overrides":
            continue
        setting = SETTINGS[name]
        deg = setting.angle
        kind = {bool: BOOL, str: STR, int: INT, float: FLOAT, tuple: FLOATS}.get(type(default))
        if kind is None:  # a field type this module does not know: fail loudly in the tests
            raise TypeError(f"NavConfig.{name}: no ROS parameter type for {default!r}")
        specs.append(
            ParamSpec(
                f"{name}_deg" if deg else name,
                _ros_default(default, deg),
                kind,
                setting.doc,
                length=len(default) if kind == FLOATS else 0,
                range=_ros_range(setting) if kind == FLOAT else None,
            )
        )
    for f in fields(ImuSpec):
        if f.name == "name":
            continue
        specs.append(
            ParamSpec(
                IMU_OVERRIDES_PREFIX + f.name,
                None,
                FLOAT,
                f"override of ImuSpec.{f.name} (SI units); unset = the imu_grade's value",
            )
        )
    return specs


def nav_config_from_params(values: Mapping[str, Any]) -> NavConfig:
    """Build and validate the NavConfig from ROS parameter values (missing or None = default).

    Raises ConfigError naming the parameter for wrong types and invalid settings.
    """
    settings: dict[str, Any] = {}
    overrides: dict[str, float] = {}
    for spec in nav_param_specs():
        raw = values.get(spec.name)
        if raw is None:
            continue
        value = spec.coerce(raw)
        if spec.name.startswith(IMU_OVERRIDES_PREFIX):
            overrides[spec.name[len(IMU_OVERRIDES_PREFIX) :]] = value
        else:
            settings[spec.name] = list(value) if isinstance(value, tuple) else value
    if overrides:
        settings["imu_overrides"] = overrides
    return NavConfig.from_dict(settings)


def nav_params_from_config(config: NavConfig) -> dict[str, Any]:
    """The ROS parameter values (degrees for angles) that reproduce a NavConfig."""
    out: dict[str, Any] = {}
    for name, value in config.to_dict().items():
        if name == "imu_overrides":
            for key, v in dict(value).items():
                out[IMU_OVERRIDES_PREFIX + key] = float(v)
            continue
        deg = name in ANGLE_FIELDS
        out[f"{name}_deg" if deg else name] = _ros_default(
            tuple(value) if isinstance(value, (list, tuple)) else value, deg, digits=None
        )
    return out


# --------------------------------------------------------------------------------------------
# Driver nodes

SOURCES = ("serial", "log", "sim")
STAMP_MODES = ("auto", "source", "clock", "synced")

DRIVER_COMMON = [
    ParamSpec("source", "sim", STR, "where samples come from: serial | log | sim"),
    ParamSpec("port", "/dev/ttyUSB0", STR, "serial: device path"),
    ParamSpec("baud", 115200, INT, "serial: baud rate"),
    ParamSpec("log_file", "", STR, "log: path of the recorder CSV log"),
    ParamSpec("rate", 1.0, FLOAT, "log/sim: playback speed factor (1 = real time)"),
    ParamSpec(
        "start_time",
        0.0,
        FLOAT,
        "log/sim: system time (s since 1970) at which the first sample is due; 0 = now + 1 s",
    ),
    ParamSpec(
        "stamps",
        "auto",
        STR,
        "header stamps: auto (serial: synced, log: source, sim: clock) | source (the source's "
        "own times) | clock (log/sim: moved onto the clock at start_time; serial: arrival time) "
        "| synced (serial: device time mapped onto the clock)",
    ),
    ParamSpec("scenario", "demo", STR, "sim: scenario name of pipe_nav_core.sim"),
    ParamSpec("seed", 0, INT, "sim: random seed"),
    ParamSpec("exit_when_done", False, BOOL, "log/sim: exit when the source is exhausted"),
]

DRIVER_SPECIFIC: dict[str, list[ParamSpec]] = {
    "imu": [
        ParamSpec("frame_id", "imu_link", STR, "header.frame_id of /imu/data"),
        ParamSpec("gyro_scale", 1.0, FLOAT, "raw angular rate unit -> rad/s"),
        ParamSpec("accel_scale", 1.0, FLOAT, "raw specific force unit -> m/s^2"),
        ParamSpec(
            "angular_velocity_variance",
            0.0,
            FLOAT,
            "per-sample gyro noise variance on the covariance diagonal, (rad/s)^2; 0 = unknown",
        ),
        ParamSpec(
            "linear_acceleration_variance",
            0.0,
            FLOAT,
            "per-sample accelerometer noise variance, (m/s^2)^2; 0 = unknown",
        ),
    ],
    "odometer": [
        ParamSpec("frame_id", "odom", STR, "header.frame_id of /odom/wheel"),
        ParamSpec("child_frame_id", "base_link", STR, "child_frame_id of /odom/wheel"),
        ParamSpec("wheel_circumference_m", 0.5, FLOAT, "odometer wheel circumference, m"),
        ParamSpec("ticks_per_turn", 1024, INT, "encoder counts per wheel turn"),
        ParamSpec("speed_window_s", 0.2, FLOAT, "speed = distance change over this window, s"),
        ParamSpec("counter_bits", 0, INT, "encoder counter width for wrap-around; 0 = no wrap"),
        ParamSpec(
            "markers_csv",
            "",
            STR,
            "log: marker passages to publish on /markers at their times (INTERFACES.md CSV)",
        ),
        ParamSpec(
            "publish_markers", True, BOOL, "log/sim: publish the marker passages on /markers"
        ),
    ],
    "mag": [
        ParamSpec("frame_id", "imu_link", STR, "header.frame_id of /imu/mag"),
        ParamSpec("field_scale", 1e-6, FLOAT, "raw field unit -> tesla (1e-6: microtesla)"),
        ParamSpec("hard_iron", [0.0, 0.0, 0.0], FLOATS, "hard-iron offset, T, imu_link", 3),
        ParamSpec(
            "soft_iron",
            [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            FLOATS,
            "soft-iron matrix, 3x3 row-major: field = soft_iron (raw - hard_iron)",
            9,
        ),
    ],
}

DRIVER_NODE_NAMES = {
    "imu": "imu_driver_node",
    "odometer": "odometer_driver_node",
    "mag": "magnetometer_driver_node",
}


def driver_param_specs(kind: str) -> list[ParamSpec]:
    return DRIVER_COMMON + DRIVER_SPECIFIC[kind]


def driver_settings_from_params(kind: str, values: Mapping[str, Any]) -> dict[str, Any]:
    """Validated driver settings (``stamps`` auto resolved); ConfigError naming the parameter.

    ``stamps`` auto means: serial -> synced, log -> source, sim -> clock.
    """
    v = values_from(driver_param_specs(kind), values)
    if v["source"] not in SOURCES:
        raise ConfigError(f"source must be one of {', '.join(SOURCES)}, not {v['source']!r}")
    if v["stamps"] not in STAMP_MODES:
        raise ConfigError(f"stamps must be one of {', '.join(STAMP_MODES)}, not {v['stamps']!r}")
    if v["source"] != "serial" and v["stamps"] == "synced":
        raise ConfigError("stamps 'synced' applies to source serial only")
    if v["rate"] <= 0:
        raise ConfigError(f"rate must be > 0, not {v['rate']!r}")
    if v["start_time"] < 0:
        raise ConfigError(f"start_time must be >= 0 (0 = now), not {v['start_time']!r}")
    if v["baud"] <= 0:
        raise ConfigError(f"baud must be > 0, not {v['baud']!r}")
    if v["source"] == "log" and not v["log_file"]:
        raise ConfigError("source 'log' needs the log_file parameter (path of the CSV log)")
    if v["source"] == "serial" and not v["port"]:
        raise ConfigError("source 'serial' needs the port parameter")
    for name in ("gyro_scale", "accel_scale", "field_scale"):
        if name in v and v[name] == 0:
            raise ConfigError(f"{name} must not be 0")
    for name in ("angular_velocity_variance", "linear_acceleration_variance"):
        if name in v and v[name] < 0:
            raise ConfigError(f"{name} must be >= 0, not {v[name]!r}")
    if v["stamps"] == "auto":
        v["stamps"] = {"serial": "synced", "log": "source", "sim": "clock"}[v["source"]]
    v["kind"] = kind
    return v


# --------------------------------------------------------------------------------------------
# ekf_node and smoother_node

EKF_NODE_SPECS = [
    ParamSpec(
        "survey_markers_csv",
        "",
        STR,
        "optional CSV of surveyed markers known in advance (INTERFACES.md marker CSV)",
    ),
    ParamSpec("publish_tf", True, BOOL, "broadcast the TF map -> base_link"),
    ParamSpec("map_frame", "map", STR, "frame of the published pose (ENU at the datum)"),
    ParamSpec("base_frame", "base_link", STR, "child frame of the published odometry"),
    ParamSpec("publish_period_s", 0.05, FLOAT, "how often new estimates are published, s"),
    ParamSpec("diagnostics_period_s", 1.0, FLOAT, "period of /diagnostics, s"),
    ParamSpec(
        "sensor_qos_depth",
        5000,
        INT,
        "history depth of the sensor subscriptions (5000: 5 s of a 1 kHz IMU if the node stalls)",
    ),
    ParamSpec(
        "sensor_qos_reliable",
        False,
        BOOL,
        "subscribe to the sensors reliable: nothing lost when the node falls behind a replay "
        "(replay.launch.py); a best-effort publisher (the drivers) then does not connect",
    ),
    ParamSpec(
        "imu_frame",
        "imu_link",
        STR,
        "frame_id accepted on imu/data and imu/mag (also <prefix>/imu_link); others: fault",
    ),
    ParamSpec(
        "odom_frame",
        "odom",
        STR,
        "frame_id accepted on odom/wheel (child: base_frame; also <prefix>/...); others: fault",
    ),
    ParamSpec(
        "max_stamp_lead_s",
        1.0,
        FLOAT,
        "a stamp this far (s) ahead of the newest sensor stamp is a fault (stamp_future)",
    ),
]

SMOOTHER_NODE_SPECS = [
    ParamSpec("bag", "", STR, "input bag: .mcap file or rosbag2 directory (required)"),
    ParamSpec("output", "", STR, "output .mcap; default <bag stem>_smoothed.mcap beside the bag"),
    ParamSpec(
        "method", "rts", STR, "smoother (smooth --method): rts | two-filter | forward | graph"
    ),
    ParamSpec("iterations", 5, INT, "smoothing passes at most, as pipe-nav smooth --iterations"),
    ParamSpec("spacing", 0.5, FLOAT, "centreline sample spacing along the chainage, m"),
    ParamSpec("markers_csv", "", STR, "optional marker CSV adding to or replacing /markers"),
    ParamSpec("csv", "", STR, "optional centreline CSV output path"),
    ParamSpec("geojson", "", STR, "optional GeoJSON output path"),
    ParamSpec("kml", "", STR, "optional KML output path"),
    ParamSpec("plot", "", STR, "optional plot output path (png/pdf/svg)"),
    ParamSpec("exit_when_done", False, BOOL, "exit after publishing; false keeps the path latched"),
    ParamSpec("diagnostics_period_s", 1.0, FLOAT, "period of progress logs and /diagnostics, s"),
]


def ekf_node_settings(values: Mapping[str, Any]) -> dict[str, Any]:
    """Validated ekf_node settings (not the estimator's); ConfigError when wrong."""
    v = values_from(EKF_NODE_SPECS, values)
    for name in ("publish_period_s", "diagnostics_period_s"):
        if v[name] <= 0:
            raise ConfigError(f"{name} must be > 0, not {v[name]!r}")
    if v["sensor_qos_depth"] < 1:
        raise ConfigError(f"sensor_qos_depth must be >= 1, not {v['sensor_qos_depth']!r}")
    if v["max_stamp_lead_s"] <= 0:
        raise ConfigError(f"max_stamp_lead_s must be > 0, not {v['max_stamp_lead_s']!r}")
    for name in ("map_frame", "base_frame", "imu_frame", "odom_frame"):
        if not v[name]:
            raise ConfigError(f"{name} must not be empty")
    return v


def smoother_node_settings(values: Mapping[str, Any]) -> dict[str, Any]:
    """Validated smoother_node settings; the output path is derived when not given."""
    from pathlib import Path

    from pipe_nav_core import bag_stem

    v = values_from(SMOOTHER_NODE_SPECS, values)
    if not v["bag"]:
        raise ConfigError("bag must name the input bag (.mcap file or rosbag2 directory)")
    bag = Path(v["bag"]).expanduser()
    if not bag.exists():
        raise ConfigError(f"bag {str(bag)!r} does not exist")
    if v["diagnostics_period_s"] <= 0:
        raise ConfigError(f"diagnostics_period_s must be > 0, not {v['diagnostics_period_s']!r}")
    if not v["method"]:
        raise ConfigError("method must not be empty")
    if v["iterations"] < 1:
        raise ConfigError(f"iterations must be >= 1, not {v['iterations']!r}")
    if v["spacing"] <= 0:
        raise ConfigError(f"spacing must be > 0, not {v['spacing']!r}")
    if not v["output"]:
        v["output"] = str(bag.parent / f"{bag_stem(bag)}_smoothed.mcap")
    out = Path(v["output"]).expanduser()
    if out.resolve() == bag.resolve():
        raise ConfigError("output must differ from the input bag")
    v["bag"], v["output"] = str(bag), str(out)
    return v


# --------------------------------------------------------------------------------------------
# Parameter files (config/ekf.yaml and config/drivers.yaml are generated with these)


def params_yaml(
    node_name: str, values: Mapping[str, Any], comments: Mapping[str, str] | None = None
) -> str:
    """A ROS parameter file of one node: ``node_name: ros__parameters:`` with the values (None:
    left out), each below its line of ``comments`` where it has one; lists in flow style.

    Written by ruamel.yaml, but so that YAML 1.1 (PyYAML, which ``ros2 param load`` uses), rcl's
    parser of ``--params-file`` and YAML 1.2 (ruamel) all read back the same values, which
    ruamel alone does not ensure: a float always has a dot (``1.0e-06``; ruamel writes
    ``1e-06``, a string to YAML 1.1), and a string is always double-quoted (ruamel writes ``on``
    plain, which YAML 1.1 and rcl read as true).
    """
    from ruamel.yaml import YAML
    from ruamel.yaml.comments import CommentedMap
    from ruamel.yaml.representer import RoundTripRepresenter
    from ruamel.yaml.scalarstring import DoubleQuotedScalarString

    class Representer(RoundTripRepresenter):
        def represent_float(self, data: float) -> Any:
            text = repr(data)  # shortest round trip; its exponent is signed, as YAML 1.1 needs
            if not math.isfinite(data) or "." in text or "e" not in text:
                return super().represent_float(data)  # .nan and .inf are read by both
            return self.represent_scalar("tag:yaml.org,2002:float", text.replace("e", ".0e"))

        def represent_list(self, data: list) -> Any:
            return self.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)

    Representer.add_representer(float, Representer.represent_float)
    Representer.add_representer(list, Representer.represent_list)
    params = CommentedMap()
    for name, value in values.items():
        if value is None:
            continue
        if isinstance(value, str):
            value = DoubleQuotedScalarString(value)
        params[name] = list(value) if isinstance(value, tuple) else value
        if comments and name in comments:
            params.yaml_set_comment_before_after_key(name, before=comments[name], indent=4)
    yaml = YAML()  # round trip: it writes comments
    yaml.Representer = Representer
    yaml.width = 1 << 16  # no line folded
    out = io.StringIO()
    yaml.dump({node_name: {"ros__parameters": params}}, out)
    return out.getvalue()


def defaults_yaml(node_name: str, specs: Sequence[ParamSpec]) -> str:
    """The parameter file of ``specs``' defaults, each below its description; the optional
    parameters of a group (``imu_overrides.<field>``, unset by default) are shown commented
    out at the end."""
    text = params_yaml(
        node_name,
        {s.name: s.default for s in specs if "." not in s.name},
        {s.name: s.description for s in specs},
    )
    nested: dict[str, list[str]] = {}
    for spec in specs:
        if "." in spec.name:
            group, member = spec.name.split(".", 1)
            nested.setdefault(group, []).append(member)
    for group, members in nested.items():
        text += f"    # {group}: optional, unset = not overridden; for example:\n"
        text += f"    # {group}:\n" + "".join(f"    #   {m}: 0.0\n" for m in members)
    return text


HEADERS = {
    "ekf": (
        "# ekf_node parameters: every estimator setting (pipe_nav_core NavConfig) with its\n"
        "# default. Angles in degrees (*_deg), everything else SI. Loaded by live.launch.py and\n"
        "# replay.launch.py (and by smooth.launch.py for smoother_node). After a change of\n"
        "# NavConfig regenerate it (in src/pipe_nav_ros, with the Python that has the core):\n"
        "#   python -m pipe_nav_ros.params ekf > config/ekf.yaml\n"
    ),
    "drivers": (
        "# Parameters of imu_driver_node, odometer_driver_node and magnetometer_driver_node\n"
        "# with their defaults; see src/pipe_nav_ros/README.md for the serial protocol and the\n"
        "# CSV log formats. Regenerate with:  python -m pipe_nav_ros.params drivers\n"
    ),
}


def config_file_text(which: str) -> str:
    """The text of config/ekf.yaml (``ekf``) or config/drivers.yaml (``drivers``)."""
    if which == "ekf":
        return HEADERS["ekf"] + defaults_yaml("ekf_node", nav_param_specs() + EKF_NODE_SPECS)
    if which == "drivers":
        parts = [HEADERS["drivers"]]
        for kind in ("imu", "odometer", "mag"):
            parts.append(defaults_yaml(DRIVER_NODE_NAMES[kind], driver_param_specs(kind)))
        return "\n".join(parts)
    raise ValueError(f"unknown config file {which!r}: ekf or drivers")


if __name__ == "__main__":
    import sys

    sys.stdout.write(config_file_text(sys.argv[1] if len(sys.argv) > 1 else "ekf"))
