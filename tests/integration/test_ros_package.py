"""pipe_nav_ros packaging without ROS: parameters and config YAML, setup.py, setup.cfg,
package.xml, launch files, scripts, and that the rclpy modules at least compile."""

from __future__ import annotations

import ast
import configparser
import dataclasses
import math
import os
import py_compile
import re
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from pipe_nav_ros.msg_types import ROS_MESSAGES
from pipe_nav_ros.params import (
    DRIVER_NODE_NAMES,
    EKF_NODE_SPECS,
    IMU_OVERRIDES_PREFIX,
    SMOOTHER_NODE_SPECS,
    config_file_text,
    driver_param_specs,
    driver_settings_from_params,
    ekf_node_settings,
    nav_config_from_params,
    nav_param_specs,
    nav_params_from_config,
    params_yaml,
    smoother_node_settings,
)

from pipe_nav_core import (
    ANGLE_FIELDS,
    SETTINGS,
    ConfigError,
    ImuSpec,
    NavConfig,
    rosmsg,
)

PKG = Path(__file__).resolve().parents[2] / "src" / "pipe_nav_ros"
NODES = {
    "imu_driver_node",
    "odometer_driver_node",
    "magnetometer_driver_node",
    "ekf_node",
    "smoother_node",
}


def load_yaml(text: str):
    try:
        import yaml  # PyYAML on a ROS machine

        return yaml.safe_load(text)
    except ImportError:
        from ruamel.yaml import YAML  # comes with rosbags

        return YAML(typ="safe", pure=True).load(text)


def params_of(path: Path, node: str) -> dict:
    data = load_yaml(path.read_text())
    return flatten(data[node]["ros__parameters"])


def flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


# ------------------------------------------------------------------------------ parameters


def test_nav_parameters_cover_every_navconfig_field():
    names = {s.name for s in nav_param_specs()}
    for f in dataclasses.fields(NavConfig):
        if f.name == "imu_overrides":
            for g in dataclasses.fields(ImuSpec):
                if g.name != "name":
                    assert IMU_OVERRIDES_PREFIX + g.name in names
        elif f.name in ANGLE_FIELDS:
            assert f"{f.name}_deg" in names, f.name
        else:
            assert f.name in names, f.name
    assert len(names) == len(nav_param_specs())


def test_nav_config_from_default_parameters_is_the_default_config():
    defaults = {s.name: s.default for s in nav_param_specs()}
    cfg = nav_config_from_params(defaults)
    ref = NavConfig()
    for f in dataclasses.fields(NavConfig):
        a, b = getattr(cfg, f.name), getattr(ref, f.name)
        if isinstance(b, (float, tuple)):
            assert a == pytest.approx(b, rel=1e-9, abs=1e-15), f.name
        else:
            assert a == b, f.name
    assert nav_config_from_params({}) == ref


def test_nav_parameters_accept_rclpy_array_values():
    import array

    import numpy as np

    cfg = nav_config_from_params(
        {
            "imu_mount_rpy_deg": array.array("d", [0.0, 0.0, 90.0]),  # rclpy DOUBLE_ARRAY
            "mag_hard_iron": array.array("q", [0, 0, 0]),  # rclpy INTEGER_ARRAY
            "odometer_lever_arm": np.array([0.0, 0.0, -0.1]),
        }
    )
    assert cfg.imu_mount_rpy == pytest.approx((0.0, 0.0, math.pi / 2))
    assert cfg.odometer_lever_arm == pytest.approx((0.0, 0.0, -0.1))


def test_nav_parameters_conversions_and_errors():
    cfg = nav_config_from_params(
        {
            "filter_rate_hz": 20,  # integer for a double
            "initial_azimuth_deg": 90,
            "imu_mount_rpy_deg": [0, 0, 180],
            "imu_overrides.gyro_arw": 1e-4,
            "imu_overrides.accel_vrw": None,  # unset
            "mode": "dr",
        }
    )
    assert cfg.filter_rate_hz == 20.0 and cfg.mode == "dr"
    assert cfg.initial_azimuth == pytest.approx(math.pi / 2)
    assert cfg.imu_mount_rpy == pytest.approx((0.0, 0.0, math.pi))
    assert dict(cfg.imu_overrides) == {"gyro_arw": 1e-4}
    assert cfg.imu_spec().gyro_arw == 1e-4
    back = nav_config_from_params(nav_params_from_config(cfg))
    for f in dataclasses.fields(NavConfig):
        a, b = getattr(back, f.name), getattr(cfg, f.name)
        if isinstance(b, (float, tuple)):
            assert a == pytest.approx(b, rel=1e-15, abs=1e-18), f.name
        else:
            assert a == b, f.name


@pytest.mark.parametrize(
    "values, name",
    [
        ({"mode": "magic"}, "mode"),
        ({"filter_rate_hz": "ten"}, "filter_rate_hz"),
        ({"filter_rate_hz": -1.0}, "filter_rate_hz"),
        ({"zupt_sigma": float("nan")}, "zupt_sigma"),
        ({"mag_update": 1}, "mag_update"),
        ({"odometer_lever_arm": [0.0, 0.0]}, "odometer_lever_arm"),
        ({"imu_grade": "military"}, "imu_grade"),
        ({"gate_probability": 1.5}, "gate_probability"),
        ({"imu_overrides.gyro_arw": "x"}, "imu_overrides.gyro_arw"),
    ],
)
def test_invalid_nav_parameters_name_the_parameter(values, name):
    with pytest.raises(ConfigError, match=re.escape(name)):
        nav_config_from_params(values)


def test_node_settings():
    assert ekf_node_settings({})["publish_tf"] is True
    with pytest.raises(ConfigError, match="publish_period_s"):
        ekf_node_settings({"publish_period_s": 0.0})
    with pytest.raises(ConfigError, match="sensor_qos_depth"):
        ekf_node_settings({"sensor_qos_depth": 0})
    with pytest.raises(ConfigError, match="bag"):
        smoother_node_settings({})
    with pytest.raises(ConfigError, match="does not exist"):
        smoother_node_settings({"bag": "/nonexistent/x.mcap"})


def test_smoother_settings_derive_the_output(tmp_path):
    bag = tmp_path / "run.mcap"
    bag.write_bytes(b"")
    s = smoother_node_settings({"bag": str(bag)})
    assert s["output"] == str(tmp_path / "run_smoothed.mcap")
    with pytest.raises(ConfigError, match="differ"):
        smoother_node_settings({"bag": str(bag), "output": str(bag)})
    names = [spec.name for spec in SMOOTHER_NODE_SPECS]
    assert len(names) == len(set(names))


def test_smoother_node_and_launch_offer_the_methods_of_pipe_nav_smooth():
    """The method parameter's default and choices are pipe-nav smooth's (smooth.methods): the
    node and the launch file cannot drift to another default."""
    from pipe_nav_core.smooth.methods import DEFAULT_METHOD, METHODS

    spec = next(s for s in SMOOTHER_NODE_SPECS if s.name == "method")
    assert spec.default == DEFAULT_METHOD
    assert set(re.findall(r"[a-z-]+", spec.description.partition(":")[2])) == set(METHODS)
    default, description = _smooth_launch_argument("method")
    assert default == DEFAULT_METHOD
    assert set(METHODS) <= set(re.findall(r"[a-z-]+", description))


def test_smoother_node_and_launch_run_as_many_passes_as_pipe_nav_smooth():
    """The iterations parameter's default is pipe-nav smooth's (smooth.methods.MAX_PASSES)."""
    from pipe_nav_core.smooth.methods import MAX_PASSES

    assert next(s for s in SMOOTHER_NODE_SPECS if s.name == "iterations").default == MAX_PASSES
    assert _smooth_launch_argument("iterations")[0] == str(MAX_PASSES)


def _smooth_launch_argument(name: str) -> tuple[str, str]:
    """(default, description) of smooth.launch.py's argument ``name``, declared once."""
    launch = ast.parse((PKG / "launch" / "smooth.launch.py").read_text())
    declared = [
        n.elts for n in ast.walk(launch)
        if isinstance(n, ast.Tuple) and n.elts and getattr(n.elts[0], "value", None) == name
    ]  # fmt: skip
    assert len(declared) == 1, name
    return declared[0][1].value, declared[0][2].value


def test_nav_parameter_descriptions_and_ranges_come_from_the_settings():
    """Each NavConfig parameter's description is its Setting.doc, and a double's range is its
    rule's bounds (degrees for angles, the largest double for no bound): it holds the default,
    and a value outside it is refused by the validation too."""
    big = 1.7976931348623157e308
    ranges = {}
    for spec in nav_param_specs():
        if spec.name.startswith(IMU_OVERRIDES_PREFIX):
            continue
        name = spec.name.removesuffix("_deg") if spec.name.endswith("_deg") else spec.name
        assert (name in ANGLE_FIELDS) == spec.name.endswith("_deg"), spec.name
        assert spec.description == SETTINGS[name].doc, spec.name
        bounded = spec.kind == "float" and SETTINGS[name].rule.bounds() is not None
        assert (spec.range is not None) == bounded, spec.name
        ranges[spec.name] = spec.range
        if spec.range is None:
            continue
        low, high = spec.range
        assert low <= spec.default <= high, spec.name
        for outside in (low - 1.0, high * 2.0 if high < big else None):
            if outside is not None:
                with pytest.raises(ConfigError, match=re.escape(name)):
                    nav_config_from_params({spec.name: outside})
    assert ranges["filter_rate_hz"] == (0.0, 1000.0)
    assert ranges["gate_probability"] == (0.5, 1.0)
    assert ranges["zupt_sigma"] == ranges["bend_min_angle_deg"] == (0.0, big)
    assert ranges["odometer_resolution"] == (0.0, big)
    assert ranges["initial_azimuth_deg"] is None and ranges["mag_declination_deg"] is None


def _both_yaml_readers():
    """PyYAML (YAML 1.1, as `ros2 param load` reads files) and ruamel (YAML 1.2) loaders."""
    import yaml  # PyYAML
    from ruamel.yaml import YAML

    return [yaml.safe_load, YAML(typ="safe", pure=True).load]


AWKWARD = {
    "small": 1e-5,
    "big": 1e20,
    "tenth": 0.1,
    "negative_zero": -0.0,
    "large_int_as_float": 1e16,
    "huge_int_as_float": 123456789012345678.0,
    "tiny": 5e-324,
    "negative_small": -2.5e-7,
    "ten": 10.0,
    "integer": 7,
    "flag": False,
    "on_string": "on",
    "number_string": "1e-05",
    "empty": "",
    "quotes": 'say "x" \\ y',
    "floats": [1e-5, 1e20, -0.0, 0.1],
}


def test_parameter_files_read_back_the_same_under_yaml_1_1_and_1_2():
    """params_yaml's files give every default of every node and awkward values back with
    their type under both YAML versions (where the float representer is needed: YAML 1.1 reads
    ``1e-05`` as a string)."""
    specs = nav_param_specs() + EKF_NODE_SPECS + SMOOTHER_NODE_SPECS
    specs += [s for kind in DRIVER_NODE_NAMES for s in driver_param_specs(kind)]
    cases = [{s.name: s.default for s in specs if s.default is not None}, AWKWARD]
    cases.append(nav_params_from_config(NavConfig.from_dict({"imu_mount_rpy_deg": [0, 5, 90]})))
    for values in cases:
        text = params_yaml("node", values)
        for load in _both_yaml_readers():
            got = load(text)["node"]["ros__parameters"]
            assert list(got) == list(values)
            for name, value in values.items():
                assert got[name] == value and type(got[name]) is type(value), (name, got[name])
                if isinstance(value, float) and value == 0.0:
                    assert math.copysign(1.0, got[name]) == math.copysign(1.0, value), name
    assert _both_yaml_readers()[0]("v: 1e-05")["v"] == "1e-05"  # the YAML 1.1 trap


def test_config_files_are_commented_by_the_descriptions():
    """In config/ekf.yaml each parameter's line follows its description's: for the NavConfig
    parameters the field's Setting.doc."""
    lines = (PKG / "config" / "ekf.yaml").read_text().splitlines()
    for spec in nav_param_specs() + EKF_NODE_SPECS:
        if spec.default is None:
            continue
        i = lines.index(next(line for line in lines if line.startswith(f"    {spec.name}: ")))
        assert lines[i - 1] == f"    # {spec.description}", spec.name


# ------------------------------------------------------------------------------ config files


def test_ekf_yaml_holds_every_setting_with_its_default():
    params = params_of(PKG / "config" / "ekf.yaml", "ekf_node")
    specs = {s.name: s for s in nav_param_specs() + EKF_NODE_SPECS}
    unknown = set(params) - set(specs)
    assert not unknown, f"ekf.yaml has unknown parameters {unknown}"
    missing = {n for n, s in specs.items() if s.default is not None} - set(params)
    assert not missing, (
        f"ekf.yaml lacks {missing}; regenerate: "
        "cd src/pipe_nav_ros && ../../.venv/bin/python -m pipe_nav_ros.params ekf > config/ekf.yaml"
    )
    for name, value in params.items():
        default = specs[name].default
        if isinstance(default, (float, list)):
            assert value == pytest.approx(default, rel=1e-9), name
        else:
            assert value == default, name
    cfg = nav_config_from_params(params)  # validates
    assert cfg == nav_config_from_params({s.name: s.default for s in nav_param_specs()})
    ekf_node_settings(params)


def test_drivers_yaml_sections_are_valid():
    for kind, node in DRIVER_NODE_NAMES.items():
        params = params_of(PKG / "config" / "drivers.yaml", node)
        assert set(params) == {s.name for s in driver_param_specs(kind)}
        driver_settings_from_params(kind, params)


def test_config_files_are_the_generated_ones():
    for which in ("ekf", "drivers"):
        assert (PKG / "config" / f"{which}.yaml").read_text() == config_file_text(which), (
            f"config/{which}.yaml is out of date; regenerate: cd src/pipe_nav_ros && "
            f"../../.venv/bin/python -m pipe_nav_ros.params {which} > config/{which}.yaml"
        )


# ------------------------------------------------------------------------------ packaging


def setup_nodes() -> dict[str, str]:
    """The NODES table of setup.py (console entry points), read without running setup.py."""
    for node in ast.walk(ast.parse((PKG / "setup.py").read_text())):
        target = node.targets[0] if isinstance(node, ast.Assign) else None
        if isinstance(target, ast.Name) and target.id == "NODES":
            return ast.literal_eval(node.value)
    raise AssertionError("setup.py has no NODES table")


def test_setup_py_declares_the_five_nodes():
    nodes = setup_nodes()
    assert set(nodes) == NODES
    for name, target in nodes.items():
        module, func = target.split(":")
        path = PKG / (module.replace(".", "/") + ".py")
        assert path.is_file(), target
        defined = {
            n.name for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef)
        }
        assert func in defined, f"{name}: {func} not defined in {path.name}"


def test_setup_py_data_files_exist():
    text = (PKG / "setup.py").read_text()
    for needed in (
        "share/ament_index/resource_index/packages",
        'f"share/{PACKAGE}", ["package.xml"',
        "launch/*.launch.py",
        "config/*.yaml",
        'f"lib/{PACKAGE}"',
    ):
        assert needed in text, needed
    assert (PKG / "resource" / "pipe_nav_ros").is_file()
    assert (PKG / "README.md").is_file()
    assert sorted(p.name for p in (PKG / "launch").glob("*.launch.py")) == [
        "live.launch.py",
        "replay.launch.py",
        "smooth.launch.py",
    ]
    assert {p.name for p in (PKG / "config").glob("*.yaml")} == {
        "ekf.yaml",
        "drivers.yaml",
        "recorder_qos.yaml",
        "player_qos.yaml",
    }
    script = PKG / "scripts" / "replay_with_ros.sh"
    assert os.access(script, os.X_OK), "replay_with_ros.sh must be executable"


def test_setup_cfg_installs_scripts_where_ros2_run_looks():
    cfg = configparser.ConfigParser()
    cfg.read(PKG / "setup.cfg")
    assert cfg["develop"]["script_dir"] == "$base/lib/pipe_nav_ros"
    assert cfg["install"]["install_scripts"] == "$base/lib/pipe_nav_ros"


def test_package_xml():
    root = ET.parse(PKG / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "pipe_nav_ros"
    assert root.find("export/build_type").text == "ament_python"
    deps = {e.text for e in root.findall("exec_depend")}
    for dep in (
        "rclpy",
        "sensor_msgs",
        "nav_msgs",
        "geometry_msgs",
        "std_msgs",
        "std_srvs",
        "diagnostic_msgs",
        "builtin_interfaces",
        "rcl_interfaces",
        "tf2_ros_py",
        "launch",
        "launch_ros",
        "ros2bag",
        "rosbag2_storage_mcap",
        "python3-numpy",
        "python3-scipy",
        "python3-serial",
        "pipe_nav_core",
    ):
        assert dep in deps, dep
    assert {e.text for e in root.findall("test_depend")} == {"python3-pytest"}


def test_every_ros_import_is_a_declared_dependency():
    """The ROS packages imported by the nodes and launch files are exec_depends."""
    deps = {e.text for e in ET.parse(PKG / "package.xml").getroot().findall("exec_depend")}
    provided_by = {"tf2_ros": "tf2_ros_py", "yaml": "python3-yaml", "serial": "python3-serial"}
    files = list((PKG / "pipe_nav_ros").glob("*.py")) + list((PKG / "launch").glob("*.py"))
    stdlib_or_local = {"pipe_nav_ros", "pipe_nav_core", "numpy", "__future__"}
    stdlib_or_local.add("ruamel")  # a dependency of pipe_nav_core, installed with it (pip)
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                top = node.module.split(".")[0]
            elif isinstance(node, ast.Import):
                top = node.names[0].name.split(".")[0]
            else:
                continue
            if top in stdlib_or_local or top in __import__("sys").stdlib_module_names:
                continue
            assert provided_by.get(top, top) in deps, f"{path.name} imports {top}"


def test_msg_types_table_names_real_jazzy_messages():
    ts = rosmsg.jazzy_typestore()
    for field, (package, name) in ROS_MESSAGES.items():
        assert f"{package}/msg/{name}" in ts.types, field
    message_fields = {f.name for f in dataclasses.fields(rosmsg.MsgTypes)} - {"byte_as_bytes"}
    assert message_fields <= set(ROS_MESSAGES)


# ------------------------------------------------------------------------------ code and launch


def test_all_modules_and_launch_files_compile(tmp_path):
    files = list((PKG / "pipe_nav_ros").glob("*.py")) + list((PKG / "launch").glob("*.py"))
    files.append(PKG / "setup.py")
    for i, path in enumerate(files):
        py_compile.compile(str(path), cfile=str(tmp_path / f"{i}.pyc"), doraise=True)


def test_launch_files_reference_existing_executables():
    for path in (PKG / "launch").glob("*.launch.py"):
        text = path.read_text()
        tree = ast.parse(text)
        assert any(
            isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description"
            for n in tree.body
        )
        executables = set(re.findall(r'executable="([^"]+)"', text))
        executables |= {t for t in re.findall(r'"(\w+_node)"', text) if t.endswith("driver_node")}
        assert executables, path.name
        assert executables <= NODES, (path.name, executables - NODES)
        assert "package=PACKAGE" in text and 'PACKAGE = "pipe_nav_ros"' in text


def test_replay_launch_plays_with_clock_and_records_mcap():
    text = re.sub(r"\s+", "", (PKG / "launch" / "replay.launch.py").read_text())
    assert '"ros2","bag","play",bag,"--clock"' in text
    assert '"ros2","bag","record","-s","mcap","-o",output' in text
    assert '"use_sim_time":True' in text
    for topic in ("/pipe_nav/odometry", "/pipe_nav/datum", "/diagnostics"):
        assert f'"{topic}"' in text
    assert "/ekf_node/finish" in text


def test_replay_script_usage():
    script = PKG / "scripts" / "replay_with_ros.sh"
    subprocess.run(["bash", "-n", str(script)], check=True)
    r = subprocess.run(["bash", str(script)], capture_output=True, text=True)
    assert r.returncode == 2 and "replay_with_ros.sh IN_BAG OUT_DIR" in r.stdout
    r = subprocess.run(["bash", str(script), "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "pipe-nav replay" in r.stdout
    r = subprocess.run(
        ["bash", str(script), "in.mcap", "out", "fast"], capture_output=True, text=True
    )
    assert r.returncode == 2 and "RATE" in r.stderr
