"""pipe-nav config: the settings file of one pig, and the settings in effect."""

from __future__ import annotations

import argparse
import re

import pytest
from pipe_nav_core.app.cli import main
from pipe_nav_core.app.commands import load_config
from pipe_nav_core.app.settings_template import TOOL_FIELDS
from pipe_nav_core.config import SETTINGS, NavConfig
from pipe_nav_core.model.sensors import GRADES


def _config_of(path) -> NavConfig:
    ns = argparse.Namespace(config=str(path), set=None, mode=None, imu_grade=None,
                            mount_rpy_deg=None)  # fmt: skip
    return load_config(ns)


def test_the_template_reads_back_as_the_defaults_and_documents_every_key(tmp_path, capsys):
    assert main(["config", "--template"]) == 0
    text = capsys.readouterr().out
    (tmp_path / "pig.yaml").write_text(text)
    assert _config_of(tmp_path / "pig.yaml") == NavConfig()
    lines = text.splitlines()
    keys = [i for i, line in enumerate(lines) if re.match(r"^[a-z_]+:", line)]
    assert len(keys) >= 10
    for i in keys:  # each setting has its description, with a unit or its choices, above it
        assert lines[i - 1].startswith("# ") or lines[i - 1].startswith("#   "), lines[i]
    assert {"imu_grade", "imu_mount_rpy_deg", "odometer_lever_arm", "pipe_diameter"} <= {
        lines[i].split(":")[0] for i in keys
    }


def test_the_datasheet_figures_apply_when_uncommented(tmp_path, capsys):
    assert main(["config", "--template"]) == 0
    text = capsys.readouterr().out
    text = text.replace("# imu_overrides:", "imu_overrides:").replace(
        "#   gyro_arw:", "  gyro_arw:"
    )
    (tmp_path / "pig.yaml").write_text(text)
    cfg = _config_of(tmp_path / "pig.yaml")
    assert cfg.imu_overrides == {"gyro_arw": pytest.approx(GRADES["industrial"].gyro_arw, 1e-5)}


def test_the_settings_in_effect_round_trip(tmp_path, capsys):
    argv = ["config", "--set", "imu_mount_rpy_deg=0,5,90", "--set", "imu_grade=tactical"]
    assert main(argv) == 0
    (tmp_path / "eff.yaml").write_text(capsys.readouterr().out)
    want = NavConfig.from_dict({"imu_mount_rpy_deg": [0, 5, 90], "imu_grade": "tactical"})
    got = _config_of(tmp_path / "eff.yaml").to_dict()
    for name, value in want.to_dict().items():  # degrees printed to 12 decimals
        assert got[name] == (pytest.approx(value, rel=1e-10) if _numeric(value) else value), name


def _numeric(value) -> bool:
    return isinstance(value, float) or (isinstance(value, tuple) and bool(value))


def test_the_template_describes_each_setting_by_its_metadata(capsys):
    """Each key's comment line is its field's Setting.doc; an angle's key ends in _deg."""
    assert main(["config", "--template"]) == 0
    lines = capsys.readouterr().out.splitlines()
    for name in TOOL_FIELDS:
        key = f"{name}_deg" if SETTINGS[name].angle else name
        i = next(i for i, line in enumerate(lines) if line.startswith(f"{key}: "))
        assert lines[i - 1] == f"# {SETTINGS[name].doc}", key
