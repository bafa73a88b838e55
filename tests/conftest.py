"""Shared pytest setup: makes src/pipe_nav_ros importable for its ROS-free conversion tests."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ROS_PKG = ROOT / "src" / "pipe_nav_ros"
if ROS_PKG.is_dir() and str(ROS_PKG) not in sys.path:
    sys.path.insert(0, str(ROS_PKG))
