"""PipeNav ROS 2 Jazzy nodes (thin wrappers around pipe_nav_core)."""
