"""PipeNav core: ROS-free navigation engine for pipeline inspection pigs.

The public API, importable from here (``from pipe_nav_core import smooth_bag, NavConfig``); each
name is imported from its module on first use, so ``import pipe_nav_core`` itself costs nothing:

- settings and errors: NavConfig, ImuSpec, PipeNavError, InputError, ConfigError, BagError
- data (SI units, radians; frames in pipe_nav_core.types): SensorLog, ImuSamples,
  OdometerSamples, MagSamples, Marker, Datum, Trajectory
- bags and files: read_bag, bag_info, write_sensor_bag, read_markers_csv, write_markers_csv,
  read_centreline_csv, write_centreline_csv
- estimation: Navigator (the live engine), GuardedNavigator (with the live fault guard),
  NavEstimate, smooth_log, SmoothResult
- the jobs of the command line and the nodes: smooth_bag, replay_bag, Outputs,
  centreline_rows, Progress
- products: integrity_report, IntegrityReport, detect_welds
- simulation and scoring: simulate, score
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_API = {
    "NavConfig": "config",
    "ImuSpec": "sensors",
    "PipeNavError": "errors",
    "InputError": "errors",
    "ConfigError": "errors",
    "BagError": "io",
    "SensorLog": "types",
    "ImuSamples": "types",
    "OdometerSamples": "types",
    "MagSamples": "types",
    "Marker": "types",
    "Datum": "types",
    "Trajectory": "types",
    "read_bag": "io",
    "bag_info": "io",
    "write_sensor_bag": "io",
    "read_markers_csv": "io",
    "write_markers_csv": "io",
    "read_centreline_csv": "io",
    "write_centreline_csv": "io",
    "Navigator": "navigator",
    "GuardedNavigator": "live_guard",
    "NavEstimate": "estimates",
    "smooth_log": "smooth.passes",
    "SmoothResult": "smooth.centreline",
    "smooth_bag": "pipeline",
    "replay_bag": "pipeline",
    "Outputs": "pipeline",
    "centreline_rows": "pipeline",
    "Progress": "progress",
    "integrity_report": "products",
    "IntegrityReport": "products",
    "detect_welds": "products.welds",
    "simulate": "sim",
    "score": "evaluation",
}
__all__ = sorted(_API)


def __getattr__(name: str) -> Any:
    """A name of the public API, imported from its module on first use."""
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_API})
