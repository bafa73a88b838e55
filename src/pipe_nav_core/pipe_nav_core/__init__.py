"""PipeNav core: ROS-free navigation engine for pipeline inspection pigs.

The public API, importable from here (``from pipe_nav_core import smooth_bag, NavConfig``); each
name is imported from its module on first use, so ``import pipe_nav_core`` itself costs nothing:

- settings and errors: NavConfig, ImuSpec, PipeNavError, InputError, ConfigError, BagError;
  SETTINGS (each NavConfig field's Setting: its doc with the unit, the rule of its values),
  ANGLE_FIELDS (the fields in radians, given in degrees): what a front end exposing every
  setting (the ROS parameters, a GUI) is built from
- data (SI units, radians; frames in pipe_nav_core.types): SensorLog, ImuSamples,
  OdometerSamples, MagSamples, Marker, Datum, Trajectory; dcm_from_quat (the rotation matrix
  of an estimate's quaternion, to turn its ENU values into the body frame)
- bags and files: read_bag, bag_info, bag_stem (a bag's name for the files made from it),
  write_sensor_bag, read_markers_csv, write_markers_csv, read_centreline_csv,
  write_centreline_csv
- estimation: Navigator (the live engine), GuardedNavigator (with the live fault guard),
  NavEstimate, smooth_log, SmoothResult; warm_live (compiles the live engine's kernels on a
  short simulated run, so a live node is ready before its first sample arrives)
- the jobs of the command line and the nodes: smooth_bag, replay_bag, Outputs,
  centreline_rows, Progress; small_pages (what a process running them calls first: numpy's
  large arrays in ordinary pages, no stalls on huge-page compaction)
- products: integrity_report, IntegrityReport, detect_welds
- simulation and scoring: simulate, score

One module is public as a module: ``rosmsg`` (``from pipe_nav_core import rosmsg``), the
conversion between ROS 2 messages and these values, shared by the ROS nodes, the bag reader and
writer and the tests. It is two dozen functions, most in matching pairs
(``imu_to_msg`` / ``imu_from_msg``, ``odometry_to_msg`` / ``odometry_from_msg``, ...) with the
message classes they build (``MsgTypes``) and the frame and covariance constants of
INTERFACES.md; a ROS integrator uses them together, reads best qualified
(``rosmsg.imu_to_msg``), and naming each here would double this list for one audience.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_API = {
    "NavConfig": "config",
    "SETTINGS": "config",
    "ANGLE_FIELDS": "config",
    "Setting": "config",
    "ImuSpec": "model.sensors",
    "PipeNavError": "errors",
    "InputError": "errors",
    "ConfigError": "errors",
    "BagError": "errors",
    "SensorLog": "types",
    "ImuSamples": "types",
    "OdometerSamples": "types",
    "MagSamples": "types",
    "Marker": "types",
    "Datum": "types",
    "Trajectory": "types",
    "dcm_from_quat": "geo.attitude",
    "read_bag": "io",
    "bag_info": "io",
    "bag_stem": "io",
    "write_sensor_bag": "io",
    "read_markers_csv": "io",
    "write_markers_csv": "io",
    "read_centreline_csv": "io",
    "write_centreline_csv": "io",
    "Navigator": "filter.navigator",
    "GuardedNavigator": "filter.live_guard",
    "NavEstimate": "filter.estimates",
    "smooth_log": "smooth.passes",
    "SmoothResult": "smooth.centreline",
    "warm_live": "warmup",
    "smooth_bag": "app.pipeline",
    "replay_bag": "app.replay",
    "Outputs": "app.outputs",
    "centreline_rows": "app.outputs",
    "Progress": "app.progress",
    "small_pages": "memory",
    "integrity_report": "products",
    "IntegrityReport": "products",
    "detect_welds": "products.welds",
    "simulate": "sim",
    "score": "bench.evaluation",
}
# public modules (see the docstring): name -> the module
_MODULES = {"rosmsg": "io.rosmsg"}
__all__ = sorted({*_API, *_MODULES})


def __getattr__(name: str) -> Any:
    """A name of the public API, imported from its module on first use."""
    if name in _MODULES:
        value = importlib.import_module(f".{_MODULES[name]}", __name__)
    elif name in _API:
        value = getattr(importlib.import_module(f".{_API[name]}", __name__), name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
