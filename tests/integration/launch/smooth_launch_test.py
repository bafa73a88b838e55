"""launch_testing test of smooth.launch.py with exit_when_done:=true on a short bag.

    python -m launch_testing.launch_test tests/integration/launch/smooth_launch_test.py

The bag: the first CROP_S seconds of bags/sample.mcap (two markers), written into the test's
directory. Active tests: smoother_node comes up, smooths the bag and publishes /pipe_nav/path
(poses in map, in time order over the bag, as many as it logs) and /pipe_nav/datum, once each,
from latched publishers (reliable + transient local); the node then exits by itself and the
launch ends. After shutdown: exit status 0, the
output bag and the centreline CSV exist and the core's reader finds the path in the bag.
"""

from __future__ import annotations

import math
import os
import re
import sys
import unittest

import launch_testing
import launch_testing.asserts
from launch import LaunchDescription
from launch.actions import IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch_testing.util import resolveProcesses
from nav_msgs.msg import Path
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from sensor_msgs.msg import NavSatFix

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from launch_support import (  # noqa: E402
    LATCHED,
    HoldUntilTestsDone,
    Probe,
    crop_sample_bag,
    launch_file,
    stamp_s,
    wait_until,
    work_dir,
)

CROP_S = 75.0  # s of the sample run: 10 s rest, agm_00 at 10 s, agm_01 at 65 s
SMOOTH_TIMEOUT_S = 180.0  # smoothing takes seconds with the kernels compiled (minutes if not)
PUBLISHED = re.compile(r"published (\d+) poses on pipe_nav/path")


def generate_test_description():
    folder = work_dir("smooth")
    bag = folder / "x.mcap"
    first, last, markers = crop_sample_bag(bag, CROP_S)
    output = folder / "x_smoothed.mcap"
    csv = folder / "x_centreline.csv"
    launch = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(launch_file("smooth.launch.py")),
        launch_arguments={
            "bag": str(bag),
            "output": str(output),
            "csv": str(csv),
            "exit_when_done": "true",
        }.items(),
    )
    context = {"output": output, "csv": csv, "bag_first": first, "bag_last": last}
    return (
        LaunchDescription([launch, HoldUntilTestsDone(), launch_testing.actions.ReadyToTest()]),
        context,
    )


class TestSmooth(unittest.TestCase):
    @classmethod
    def setUpClass(cls) -> None:
        cls.probe = Probe("smooth_launch_probe")
        cls.paths = cls.probe.record("/pipe_nav/path", Path, LATCHED)
        cls.datums = cls.probe.record("/pipe_nav/datum", NavSatFix, LATCHED)

    @classmethod
    def tearDownClass(cls) -> None:
        cls.probe.close()

    def _published_poses(self, proc_output) -> int:
        (node,) = resolveProcesses(proc_output, process="smoother_node")
        text = "".join(io.text.decode() for io in proc_output[node])
        return int(PUBLISHED.search(text).group(1))

    def test_1_path_arrives_latched(self, proc_info, proc_output, bag_first, bag_last):
        proc_info.assertWaitForStartup(process="smoother_node", timeout=30)

        def publisher_qos(topic):
            found = [p for p in self.probe.publishers(topic) if p.node_name == "smoother_node"]
            return found[0].qos_profile if found else None

        # the publishers exist from the node's start; smoothing takes seconds after that
        for topic in ("/pipe_nav/path", "/pipe_nav/datum"):
            self.assertTrue(wait_until(lambda: publisher_qos(topic), 60.0), topic)  # noqa: B023
            qos = publisher_qos(topic)
            self.assertEqual(qos.reliability, ReliabilityPolicy.RELIABLE, topic)
            self.assertEqual(qos.durability, DurabilityPolicy.TRANSIENT_LOCAL, topic)
        proc_output.assertWaitFor(PUBLISHED, process="smoother_node", timeout=SMOOTH_TIMEOUT_S)
        paths, datums = self.paths, self.datums
        self.assertTrue(wait_until(lambda: paths and datums, 20.0), "no path or datum")
        self.assertEqual((len(paths), len(datums)), (1, 1))

        path = paths[0][1]
        self.assertEqual(path.header.frame_id, "map")
        self.assertEqual(len(path.poses), self._published_poses(proc_output))
        self.assertGreater(len(path.poses), 100)  # 0.5 m spacing over about 120 m
        stamps = [stamp_s(p) for p in path.poses]
        self.assertGreaterEqual(min(b - a for a, b in zip(stamps, stamps[1:])), 0.0)
        self.assertGreaterEqual(stamps[0], bag_first - 1e-6)
        self.assertLessEqual(stamps[-1], bag_last + 1e-6)
        for pose in path.poses:
            self.assertEqual(pose.header.frame_id, "map")
            p = pose.pose.position
            self.assertTrue(all(math.isfinite(v) for v in (p.x, p.y, p.z)))
        ends = path.poses[0].pose.position, path.poses[-1].pose.position
        self.assertGreater(math.dist((ends[0].x, ends[0].y), (ends[1].x, ends[1].y)), 50.0)
        datum = datums[0][1]
        self.assertTrue(math.isfinite(datum.latitude) and math.isfinite(datum.longitude))

    def test_2_node_exits_by_itself(self, proc_info):
        proc_info.assertWaitForShutdown(process="smoother_node", timeout=30)


@launch_testing.post_shutdown_test()
class TestSmoothShutdown(unittest.TestCase):
    def test_exit_codes(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info)
        self.assertEqual(
            [n.rsplit("-", 1)[0] for n in proc_info.process_names()], ["smoother_node"]
        )

    def test_outputs(self, output, csv, bag_first, bag_last):
        from pipe_nav_core import bag_info

        self.assertTrue(output.is_file())
        info = bag_info(output)
        self.assertEqual(info.topics["/pipe_nav/path"].count, 1)
        self.assertEqual(info.topics["/pipe_nav/datum"].count, 1)
        rows = csv.read_text().splitlines()
        self.assertTrue(rows[0].startswith("time_s,distance_m,latitude_deg"))
        self.assertGreater(len(rows), 100)
