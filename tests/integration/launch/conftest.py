"""The files here are launch_testing tests, not pytest tests: launch_testing's runner executes
them (tests/integration/test_ros_launch.py runs one ``python -m launch_testing.launch_test FILE``
each), so pytest must not import them (``*_launch_test.py`` matches pytest's ``*_test.py``)."""

collect_ignore_glob = ["*_launch_test.py", "launch_support.py"]
