"""Shim so colcon (ament_python) can build this package; metadata lives in pyproject.toml.

``python_requires`` is given here as a plain string (pyproject.toml lists it as dynamic): colcon
reads a package's metadata as Python literals, and the SpecifierSet that setuptools builds from
``requires-python`` is not one.
"""

from setuptools import find_packages, setup

setup(
    python_requires=">=3.10",
    # named here, not discovered: colcon --symlink-install builds in a folder with other entries;
    # and the folder of the AOT module prebuilt for fresh installs (aot.install_prebuilt), data
    packages=[
        *find_packages(include=["pipe_nav_core", "pipe_nav_core.*"]),
        "pipe_nav_core.prebuilt",
    ],
    package_data={"pipe_nav_core.prebuilt": ["*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/pipe_nav_core"]),
        ("share/pipe_nav_core", ["package.xml"]),
    ],
)
