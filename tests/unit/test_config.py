"""NavConfig's settings metadata: every field carries one Setting (description with unit, rule,
angle or not), and validate(), ANGLE_FIELDS and the rules' ROS bounds are made from it."""

from __future__ import annotations

import math
from dataclasses import fields, replace

import pytest
from pipe_nav_core.config import ANGLE_FIELDS, SETTINGS, ConfigError, NavConfig, Setting

# One value of every shape: numbers at and around the bounds in use, non-finite ones, wrong
# types, and sequences sorted, unsorted, short and non-numeric.
CANDIDATES = [
    -1.0, 0, 0.0, 1e-9, 0.5, 0.75, 1, 1.0, 10.0, 1000, 1000.5, 1e300, math.nan, math.inf, -math.inf,
    True, "x", "ins", "dr", "on", "auto", "markers", "industrial", None, (), (1.0,), (1.0, 2.0),
    (1.0, 2.0, 3.0), (3.0, 2.0, 1.0), (0.0, 1.0, 2.0), (1.0, math.nan, 2.0), ("a", "b", "c"), {},
    {"gyro_arw": 1e-4}, {"nope": 1.0}, {"gyro_arw": "x"},
]  # fmt: skip


def _message(config: NavConfig) -> str | None:
    try:
        config.validate()
    except ConfigError as exc:
        return str(exc)
    return None


def test_every_field_has_one_setting():
    names = [f.name for f in fields(NavConfig)]
    assert list(SETTINGS) == names
    for f in fields(NavConfig):
        setting = f.metadata["setting"]
        assert isinstance(setting, Setting) and SETTINGS[f.name] is setting
        assert setting.doc and "\n" not in setting.doc, f.name
        if setting.angle:  # people give angles in degrees, and the description says so
            assert "deg" in setting.doc, f.name
    assert {n for n, s in SETTINGS.items() if s.angle} == ANGLE_FIELDS
    assert _message(NavConfig()) is None


@pytest.mark.parametrize(
    "change, message",
    [
        ({"mode": "magic"}, "mode must be 'ins' or 'dr', not 'magic'"),
        (
            {"imu_grade": "military"},
            "imu_grade must be auto, consumer, industrial, tactical, not 'military'",
        ),
        ({"imu_overrides": {"nope": 1.0}}, "imu_grade/imu_overrides: "),  # + ImuSpec's words
        ({"imu_mount_rpy": (0.0, 0.0)}, "imu_mount_rpy must be three finite numbers, not "
                                        "(0.0, 0.0)"),
        ({"filter_rate_hz": 0.0}, "filter_rate_hz must be a positive number, not 0.0"),
        ({"filter_rate_hz": 2000.0}, "filter_rate_hz must be at most 1000"),
        ({"marker_time_sigma": -1.0}, "marker_time_sigma must be a number >= 0, not -1.0"),
        ({"tilt_update": "maybe"}, "tilt_update must be auto, on or off, not 'maybe'"),
        (
            {"heading_source": "gps"},
            "heading_source must be markers, magnetometer or fixed, not 'gps'",
        ),
        ({"initial_azimuth": math.nan}, "initial_azimuth must be a finite number, not nan"),
        ({"gate_probability": 1.0}, "gate_probability must be in (0.5, 1), not 1.0"),
        (
            {"bend_class_limits": (12.0, 2.5, 150.0)},
            "bend_class_limits must be 3 positive numbers in increasing order, not "
            "(12.0, 2.5, 150.0)",
        ),
        ({"strain_thresholds": ()}, "strain_thresholds must be positive numbers in increasing "
                                    "order, not ()"),
    ],
)  # fmt: skip
def test_the_messages_people_see(change, message):
    got = _message(replace(NavConfig(), **change))
    assert got == message or (message.endswith(": ") and got.startswith(message)), got


@pytest.mark.parametrize("name", list(SETTINGS))
def test_validation_is_the_rule_of_each_setting(name):
    """For every value of CANDIDATES: validate() refuses it with the rule's message, naming the
    setting, exactly when the rule refuses it; a number the rule takes lies within its bounds."""
    rule = SETTINGS[name].rule
    refused = 0
    for value in CANDIDATES:
        config = replace(NavConfig(), **{name: value})
        problem = rule.problem(name, value, config)
        assert _message(config) == problem, (name, value)
        if problem:
            refused += 1
            assert problem.startswith(name) or problem.startswith("imu_grade/imu_overrides")
        elif rule.bounds() is not None:
            low, high = rule.bounds()
            assert low <= value <= high, (name, value)
    if name not in ("gyro_error_states", "accel_error_states", "mag_update"):  # flags: unchecked
        assert refused, f"{name}: its rule refuses nothing"


def test_the_first_invalid_setting_in_field_order_is_named():
    config = replace(NavConfig(), strain_thresholds=(), mode="magic", zupt_sigma=-1.0)
    assert _message(config).startswith("mode must be")


def test_degrees_are_taken_for_every_angle_and_nothing_else():
    for name in SETTINGS:
        value = (0.0, 0.0, 90.0) if name == "imu_mount_rpy" else 1.0
        if name in ANGLE_FIELDS:
            got = getattr(NavConfig.from_dict({f"{name}_deg": value}), name)
            assert got == pytest.approx(tuple(map(math.radians, value)) if isinstance(value, tuple)
                                        else math.radians(value)), name  # fmt: skip
        else:
            with pytest.raises(ConfigError, match="unknown setting"):
                NavConfig.from_dict({f"{name}_deg": value})


def test_config_from_dict_degrees_and_errors():
    cfg = NavConfig.from_dict({"initial_azimuth_deg": 90, "mode": "dr"})
    assert cfg.initial_azimuth == pytest.approx(math.pi / 2)
    with pytest.raises(ConfigError, match="mode"):
        NavConfig.from_dict({"mode": "magic"})
    with pytest.raises(ConfigError, match="unknown setting"):
        NavConfig.from_dict({"bogus": 1})
    with pytest.raises(ConfigError, match="zupt_sigma"):
        NavConfig.from_dict({"zupt_sigma": -1})


@pytest.mark.parametrize(
    "settings, rate",
    [
        ({"imu_grade": "tactical"}, 2.5),  # the long epochs, where they lose nothing
        ({"imu_grade": "tactical", "filter_rate_hz": 2.0}, 2.0),  # never longer than asked
        ({"imu_grade": "tactical", "mode": "dr"}, 10.0),  # measured in ins mode only
        ({"imu_grade": "tactical", "smoother_rate_hz": 20.0}, 20.0),  # given: taken
        ({"imu_grade": "industrial"}, 10.0),
        ({"imu_grade": "consumer", "filter_rate_hz": 4.0}, 4.0),
        ({"imu_grade": "auto"}, 10.0),  # the industrial figures until measured
        # a tactical IMU whose gyro scale factor is an industrial one's
        ({"imu_grade": "tactical", "imu_overrides": {"gyro_scale_factor": 1e-3}}, 10.0),
    ],
)
def test_the_smoothing_epochs_are_long_only_with_a_steady_imu(settings, rate):
    assert NavConfig.from_dict(settings).smoothing_rate_hz() == rate
