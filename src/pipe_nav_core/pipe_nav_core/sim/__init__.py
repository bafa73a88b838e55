"""Pipeline-run simulator: pipe geometry, pig motion, exact IMU, odometer, magnetometer, markers.

Typical use::

    from pipe_nav_core.sim import simulate, scenario_names, get_scenario
    run = simulate("drag180", seed=1)
    run.log      # SensorLog as recorded (what an estimator gets)
    run.truth    # Trajectory at the IMU times (what it is scored against)
    run.datum    # launch trap, origin of the map frame
    run.scenario.estimator_settings()   # honest NavConfig settings for this scenario

Modules: profiles (smooth ramps), geometry (centreline on the ellipsoid), motion (s(t), roll(t)),
kinematics (exact state and ideal IMU), imu / odometer / magnetometer / markers (sensor models),
scenarios (Scenario and the named set), run (simulate, SimRun).
"""

from __future__ import annotations

from pipe_nav_core.sim.geometry import Bend, PipeGeometry, Sag, field_features
from pipe_nav_core.sim.imu import ImuErrorModel, TriadErrors
from pipe_nav_core.sim.kinematics import KinState, evaluate
from pipe_nav_core.sim.motion import PigMotion, RollTurn, SpeedParams, Stop
from pipe_nav_core.sim.odometer import SlipEpisode
from pipe_nav_core.sim.run import SimRun, build_motion, mount_matrix, simulate
from pipe_nav_core.sim.scenarios import Scenario, get_scenario, scenario_names

__all__ = [
    "Bend",
    "ImuErrorModel",
    "KinState",
    "PigMotion",
    "PipeGeometry",
    "RollTurn",
    "Sag",
    "Scenario",
    "SimRun",
    "SlipEpisode",
    "SpeedParams",
    "Stop",
    "TriadErrors",
    "build_motion",
    "evaluate",
    "field_features",
    "get_scenario",
    "mount_matrix",
    "scenario_names",
    "simulate",
]
