"""PipeNav core: ROS-free navigation engine for pipeline inspection pigs."""

__version__ = "0.1.0"
