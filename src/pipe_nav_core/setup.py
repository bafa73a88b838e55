"""Shim so colcon (ament_python) can build this package; metadata lives in pyproject.toml."""

from setuptools import setup

setup(
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/pipe_nav_core"]),
        ("share/pipe_nav_core", ["package.xml"]),
    ],
)
