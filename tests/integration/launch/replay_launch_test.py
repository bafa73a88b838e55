"""launch_testing test of replay.launch.py with record:=true on a short bag.

    python -m launch_testing.launch_test tests/integration/launch/replay_launch_test.py

The bag: the first CROP_S seconds of bags/sample.mcap (static alignment, markers agm_00 and
agm_01), written into the test's directory, played at RATE times real time. Active tests:
ros2 bag play, ekf_node and ros2 bag record come up; the estimates appear on /pipe_nav/odometry
(map -> base_link, stamped on the bag's clock, up to its end once ekf_node's ~/finish flushed
them) with the datum; the launch then ends by itself (shutdown_when_done) without the runner
stopping it. After shutdown: every process exited with status 0, the recording directory holds
metadata.yaml and an .mcap with the estimates, and the core's bag reader opens it.
"""

from __future__ import annotations

import math
import os
import sys
import unittest

import launch_testing
import launch_testing.asserts
import yaml
from launch import LaunchDescription
from launch.actions import IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch_testing.util import resolveProcesses
from nav_msgs.msg import Odometry
from sensor_msgs.msg import NavSatFix

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from launch_support import (  # noqa: E402
    LATCHED,
    RELIABLE,
    HoldUntilTestsDone,
    Probe,
    config_file,
    crop_sample_bag,
    launch_file,
    stamp_s,
    wait_until,
    work_dir,
)

CROP_S = 75.0  # s of the sample run: 10 s rest, agm_00 at 10 s, agm_01 at 65 s
RATE = 5.0  # ros2 bag play --rate: 15 s of playback
READY_TIMEOUT_S = 180.0  # ekf_node loads its kernels in seconds; compiles them (minutes) if cold
PROCESSES = ("bag_play", "ekf_node", "bag_record", "ekf_finish")


def filter_rate_hz() -> float:
    """filter_rate_hz of the installed config/ekf.yaml (Hz): one estimate per filter epoch."""
    with open(config_file("ekf.yaml"), encoding="utf-8") as f:
        return float(yaml.safe_load(f)["ekf_node"]["ros__parameters"]["filter_rate_hz"])


def generate_test_description():
    folder = work_dir("replay")
    bag = folder / "short.mcap"
    first, last, markers = crop_sample_bag(bag, CROP_S)
    output = folder / "short_ekf"
    launch = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(launch_file("replay.launch.py")),
        launch_arguments={
            "bag": str(bag),
            "record": "true",
            "output": str(output),
            "rate": str(RATE),
            "shutdown_when_done": "true",
        }.items(),
    )
    context = {"output": output, "bag_first": first, "bag_last": last, "bag_markers": markers}
    return (
        LaunchDescription([launch, HoldUntilTestsDone(), launch_testing.actions.ReadyToTest()]),
        context,
    )


class TestReplay(unittest.TestCase):
    @classmethod
    def setUpClass(cls) -> None:
        cls.probe = Probe("replay_launch_probe")
        cls.odometry = cls.probe.record("/pipe_nav/odometry", Odometry, RELIABLE)
        cls.datum = cls.probe.record("/pipe_nav/datum", NavSatFix, LATCHED)

    @classmethod
    def tearDownClass(cls) -> None:
        cls.probe.close()

    def test_1_processes_come_up(self, proc_info, proc_output):
        for name in ("ekf_node", "bag_record"):
            proc_info.assertWaitForStartup(process=name, timeout=30)
        proc_output.assertWaitFor("ekf_node ready", process="ekf_node", timeout=READY_TIMEOUT_S)
        self.assertTrue(wait_until(lambda: "ekf_node" in self.probe.node_names(), 20.0))
        # the bag plays once ekf_node is ready and the recorder subscribed
        proc_info.assertWaitForStartup(process="bag_play", timeout=30)

    def test_2_estimates_follow_the_bag(self, proc_info, bag_first, bag_last):
        duration = bag_last - bag_first
        self.assertTrue(wait_until(lambda: self.odometry, 30.0 + duration / RATE), "no estimates")
        proc_info.assertWaitForShutdown(process="bag_play", timeout=60 + duration / RATE)
        proc_info.assertWaitForShutdown(process="ekf_finish", timeout=60)
        stamps = [stamp_s(m) for _, m in self.odometry]
        gap = max(b - a for a, b in zip(stamps, stamps[1:]))
        print(
            f"{len(stamps)} estimates, {stamps[0] - bag_first:.2f} s to "
            f"{stamps[-1] - bag_first:.2f} s of the {duration:.2f} s bag, largest gap {gap:.2f} s"
        )
        for _, msg in self.odometry:
            self.assertEqual((msg.header.frame_id, msg.child_frame_id), ("map", "base_link"))
            p = msg.pose.pose.position
            self.assertTrue(all(math.isfinite(v) for v in (p.x, p.y, p.z)))
        self.assertGreater(min(b - a for a, b in zip(stamps, stamps[1:])), 0.0)
        # on the bag's clock, from the end of the static alignment to the end of the bag
        self.assertGreaterEqual(stamps[0], bag_first)
        self.assertLessEqual(stamps[-1], bag_last + 1e-6)
        self.assertGreater(stamps[-1], bag_last - 2.0, "estimates stop before the bag's end")
        # about one estimate per filter epoch over the time covered, but for epochs whose IMU
        # samples a loaded machine made ekf_node drop (counted in /diagnostics)
        epochs = (stamps[-1] - stamps[0]) * filter_rate_hz()
        self.assertGreater(len(stamps), 0.5 * epochs)
        self.assertTrue(self.datum, "no datum")
        self.assertEqual(len(self.datum), 1)

    def test_3_launch_ends_by_itself(self, proc_info):
        """After the flush the launch's own Shutdown stops ekf_node and the recorder (the runner
        stops nothing before the active tests end)."""
        for name in ("ekf_node", "bag_record"):
            proc_info.assertWaitForShutdown(process=name, timeout=30)
        self.assertEqual(
            sorted(n.rsplit("-", 1)[0] for n in proc_info.process_names()), sorted(PROCESSES)
        )


@launch_testing.post_shutdown_test()
class TestReplayShutdown(unittest.TestCase):
    def test_exit_codes(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info)

    def test_finish_flushed(self, proc_output):
        (finish,) = resolveProcesses(proc_output, process="ekf_finish")
        text = "".join(io.text.decode() for io in proc_output[finish])
        self.assertIn("success=True", text)

    def test_recording(self, output, bag_first, bag_last):
        from pipe_nav_core import bag_info

        self.assertTrue((output / "metadata.yaml").is_file(), sorted(output.iterdir()))
        mcaps = sorted(output.glob("*.mcap"))
        self.assertEqual(len(mcaps), 1, sorted(output.iterdir()))
        meta = yaml.safe_load((output / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        self.assertEqual(meta["storage_identifier"], "mcap")
        counts = {
            t["topic_metadata"]["name"]: t["message_count"]
            for t in meta["topics_with_message_count"]
        }
        print("recorded:", counts)
        self.assertGreater(counts.get("/pipe_nav/odometry", 0), 100)
        self.assertEqual(counts.get("/pipe_nav/datum"), 1)
        self.assertGreater(counts.get("/diagnostics", 0), 0)
        info = bag_info(output)  # the core reads the directory as a bag
        self.assertEqual(info.topics["/pipe_nav/odometry"].count, counts["/pipe_nav/odometry"])
        self.assertGreaterEqual(info.topics["/pipe_nav/odometry"].start, bag_first)
        self.assertLessEqual(info.topics["/pipe_nav/odometry"].end, bag_last + 1e-6)
