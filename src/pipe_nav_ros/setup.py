"""ament_python packaging of pipe_nav_ros (built by ``colcon build`` from the repository root)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "pipe_nav_ros"

# console entry points: ros2 run pipe_nav_ros <name>
NODES = {
    "imu_driver_node": "pipe_nav_ros.driver_node:main_imu",
    "odometer_driver_node": "pipe_nav_ros.driver_node:main_odometer",
    "magnetometer_driver_node": "pipe_nav_ros.driver_node:main_magnetometer",
    "ekf_node": "pipe_nav_ros.ekf_node:main",
    "smoother_node": "pipe_nav_ros.smoother_node:main",
}

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "tests"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "README.md"]),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
        # executables beside the nodes, so ros2 run finds them
        (f"lib/{PACKAGE}", sorted(glob("scripts/*.sh"))),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="PipeNav",
    maintainer_email="dev@pipenav.example",
    description="ROS 2 Jazzy nodes of PipeNav (drivers, ekf_node, smoother_node).",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={"console_scripts": [f"{name} = {target}" for name, target in NODES.items()]},
)
