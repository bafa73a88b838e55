"""launch_testing test of live.launch.py: the simulated demo run at twice real time.

    python -m launch_testing.launch_test tests/integration/launch/live_launch_test.py

Active tests: the three drivers and ekf_node come up; /imu/data, /odom/wheel and /imu/mag
arrive at the demo scenario's rates times ``rate`` (wall clock, generous tolerance) with the
scenario's sample intervals in their stamps (tight); the markers give ekf_node its datum;
/pipe_nav/odometry, TF map -> base_link and ekf_node's /diagnostics appear. After the runner
stops the launch (SIGINT): every process exited with status 0 and printed no traceback.
"""

from __future__ import annotations

import math
import os
import re
import sys
import unittest

import launch_testing
import launch_testing.asserts
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from launch import LaunchDescription
from launch.actions import IncludeLaunchDescription
from launch.events.process import ProcessExited
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch_testing.util import resolveProcesses
from nav_msgs.msg import Odometry
from pipe_nav_core.sim import get_scenario
from sensor_msgs.msg import Imu, MagneticField, NavSatFix
from tf2_msgs.msg import TFMessage

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from launch_support import (  # noqa: E402
    LATCHED,
    RELIABLE,
    SENSOR,
    Probe,
    launch_file,
    median_step,
    stamp_s,
    wait_until,
)

SCENARIO = "demo"
# Playback speed factor. Faster is no shorter a test (it needs the first marker, 10 s into the
# run, and a few s of data) but tighter for ekf_node: its reorder window (0.5 s of stamps) is
# 0.5 s / RATE of wall time by which the three drivers' processes may drift apart.
RATE = 2.0
STARTUP_DELAY_S = 5.0  # from ekf_node ready (the drivers' start) to the first sample
NODES = {"imu_driver_node", "odometer_driver_node", "magnetometer_driver_node", "ekf_node"}
READY_TIMEOUT_S = 180.0  # ekf_node loads its kernels in seconds; compiles them (minutes) if cold
CAUGHT_UP_S = 0.1  # a sample arriving this close to its due time: the driver keeps time
SETTLE_S = 0.5  # s after that before rates are measured
WINDOW_S = 3.0  # s of arrivals a rate is measured over, from when the drivers keep time
WALL_RATE_TOLERANCE = 0.4  # relative: wall-clock rates depend on the machine's load
STAMP_STEP_TOLERANCE = 0.02  # relative: the stamps keep the sensors' own sample intervals
DUE = re.compile(r"first sample due at ([0-9.]+) \(system time\), rate x([0-9.]+)")


def generate_test_description():
    launch = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(launch_file("live.launch.py")),
        launch_arguments={
            "source": "sim",
            "scenario": SCENARIO,
            "seed": "0",
            "rate": str(RATE),
            "startup_delay": str(STARTUP_DELAY_S),
        }.items(),
    )
    return LaunchDescription([launch, launch_testing.actions.ReadyToTest()])


class TestLiveGraph(unittest.TestCase):
    @classmethod
    def setUpClass(cls) -> None:
        cls.probe = Probe("live_launch_probe")
        p = cls.probe
        cls.imu = p.record("/imu/data", Imu, SENSOR)
        cls.odo = p.record("/odom/wheel", Odometry, SENSOR)
        cls.mag = p.record("/imu/mag", MagneticField, SENSOR)
        cls.odometry = p.record("/pipe_nav/odometry", Odometry, RELIABLE)
        cls.datum = p.record("/pipe_nav/datum", NavSatFix, LATCHED)
        cls.markers = p.record("/markers", NavSatFix, LATCHED)
        cls.diagnostics = p.record("/diagnostics", DiagnosticArray, RELIABLE)
        cls.tf = p.record("/tf", TFMessage, RELIABLE)
        cls.scenario = get_scenario(SCENARIO)
        cls.keeping_time_since = None

    @classmethod
    def tearDownClass(cls) -> None:
        cls.probe.close()

    def _start_time(self, proc_output) -> float:
        """The drivers' shared start time (system time, s), from the IMU driver's log."""
        proc_output.assertWaitFor(DUE, process="imu_driver_node", timeout=60)
        (imu_driver,) = resolveProcesses(proc_output, process="imu_driver_node")
        text = "".join(io.text.decode() for io in proc_output[imu_driver])
        start, rate = DUE.search(text).groups()
        self.assertEqual(float(rate), RATE)
        return float(start)

    def _due(self, start: float, msg) -> float:
        """When the driver should publish ``msg``: stamps are start + (t - t0), due times
        start + (t - t0) / rate (system time, s)."""
        return start + (stamp_s(msg) - start) / RATE

    def _keeping_time_since(self, proc_output) -> float:
        """System time (s) from which the IMU driver publishes each sample at its due time.

        A driver ready after the shared start time first publishes the overdue samples at once
        (on a loaded machine the simulation at start-up takes several seconds); rates are
        measured after that."""
        if self.keeping_time_since is None:
            start = self._start_time(proc_output)

            def caught_up():
                return next((t for t, m in self.imu if t - self._due(start, m) < CAUGHT_UP_S), None)

            self.assertTrue(wait_until(lambda: caught_up() is not None, 90.0), "IMU never on time")
            since = caught_up() + SETTLE_S
            first = self.imu[0][0] - self._due(start, self.imu[0][1])
            print(f"IMU driver: first sample {first:.2f} s late, on time from {since:.3f}")
            type(self).keeping_time_since = since
        return self.keeping_time_since

    def _rate(self, received, name, since):
        """(arrival rate over WINDOW_S from ``since`` (Hz), median stamp step there (s))."""
        end = since + WINDOW_S
        self.assertTrue(
            wait_until(lambda: received and received[-1][0] >= end, WINDOW_S + 30.0),
            f"{name} stopped after {len(received)} messages",
        )
        window = [(t, m) for t, m in received if since <= t < end]
        self.assertGreater(len(window), 10, name)
        rate = (len(window) - 1) / (window[-1][0] - window[0][0])
        return rate, median_step([stamp_s(m) for _, m in window])

    def _check_sensor(self, received, name, scenario_hz, since):
        rate, step = self._rate(received, name, since)
        expected = scenario_hz * RATE
        print(f"{name}: {rate:.1f} Hz (expected {expected:.0f}), stamp step {step * 1e3:.2f} ms")
        self.assertLess(
            abs(rate - expected), WALL_RATE_TOLERANCE * expected, f"{name} at {rate:.1f} Hz"
        )
        self.assertAlmostEqual(
            step, 1.0 / scenario_hz, delta=STAMP_STEP_TOLERANCE / scenario_hz, msg=name
        )

    def test_1_processes_and_nodes_come_up(self, proc_output):
        proc_output.assertWaitFor("ekf_node ready", process="ekf_node", timeout=READY_TIMEOUT_S)
        for driver in sorted(NODES - {"ekf_node"}):  # started once ekf_node is ready
            proc_output.assertWaitFor("sim source ready", process=driver, timeout=60)
        names = self.probe.node_names
        self.assertTrue(wait_until(lambda: names() >= NODES, 20.0), f"nodes seen: {names()}")

    def test_2_imu_at_its_rate(self, proc_output):
        since = self._keeping_time_since(proc_output)
        self._check_sensor(self.imu, "/imu/data", self.scenario.imu_rate_hz, since)
        msg = self.imu[-1][1]
        self.assertEqual(msg.header.frame_id, "imu_link")
        self.assertEqual(msg.orientation_covariance[0], -1.0)
        # specific force: about g (9.8 m/s^2) on average, whatever the attitude
        forces = sorted(
            math.sqrt(a.x**2 + a.y**2 + a.z**2)
            for a in (m.linear_acceleration for _, m in self.imu)
        )
        self.assertAlmostEqual(forces[len(forces) // 2], 9.8, delta=0.3)

    def test_3_odometer_and_magnetometer_at_their_rates(self, proc_output):
        since = self._keeping_time_since(proc_output)
        self._check_sensor(self.odo, "/odom/wheel", self.scenario.odo_rate_hz, since)
        self._check_sensor(self.mag, "/imu/mag", self.scenario.mag_rate_hz, since)
        distances = [m.pose.pose.position.x for _, m in self.odo]
        self.assertGreaterEqual(min(b - a for a, b in zip(distances, distances[1:])), -1e-9)
        self.assertEqual(self.odo[-1][1].header.frame_id, "odom")
        self.assertEqual(self.odo[-1][1].child_frame_id, "base_link")

    def test_4_markers_give_the_datum(self):
        self.assertTrue(wait_until(lambda: self.markers and self.datum, 30.0))
        self.assertTrue(self.markers[0][1].header.frame_id.startswith("agm_"))
        datum = self.datum[-1][1]
        self.assertAlmostEqual(datum.latitude, math.degrees(self.scenario.lat), delta=0.01)
        self.assertAlmostEqual(datum.longitude, math.degrees(self.scenario.lon), delta=0.01)

    def test_5_estimates_and_tf_appear(self):
        self.assertTrue(wait_until(lambda: len(self.odometry) >= 10, 60.0), "no estimates")
        for _, msg in self.odometry:
            self.assertEqual((msg.header.frame_id, msg.child_frame_id), ("map", "base_link"))
            p = msg.pose.pose.position
            self.assertTrue(
                all(math.isfinite(v) for v in (p.x, p.y, p.z)), f"estimate {stamp_s(msg)}: {p}"
            )
        stamps = [stamp_s(m) for _, m in self.odometry]
        self.assertGreater(min(b - a for a, b in zip(stamps, stamps[1:])), 0.0)
        # the estimates follow the sensors: stamped on the drivers' clock, a few s behind at most
        imu_latest = stamp_s(self.imu[-1][1])
        self.assertLess(abs(imu_latest - stamps[-1]), 10.0 * RATE)
        self.assertTrue(
            wait_until(
                lambda: any(
                    t.child_frame_id == "base_link" and t.header.frame_id == "map"
                    for _, m in self.tf
                    for t in m.transforms
                ),
                10.0,
            ),
            "no TF map -> base_link",
        )

    def test_6_ekf_diagnostics(self, proc_output):
        """ekf_node's own report: it receives the drivers' streams at their rates (once the
        drivers keep time and ekf_node has worked off what a late start sent at once)."""
        since = self._keeping_time_since(proc_output)
        expected = {
            "imu": self.scenario.imu_rate_hz * RATE,
            "odometer": self.scenario.odo_rate_hz * RATE,
        }

        def reports():
            return [
                (status, {v.key: v.value for v in status.values})
                for _, array in self.diagnostics
                if stamp_s(array) >= since + 1.5
                for status in array.status
                if status.name == "pipe_nav: ekf_node"
            ]

        def at_rate(values):
            return all(
                abs(float(values[f"{role}.rate_hz"]) - hz) < WALL_RATE_TOLERANCE * hz
                for role, hz in expected.items()
            )

        found = wait_until(lambda: any(at_rate(v) for _, v in reports()), 20.0)
        self.assertTrue(reports(), "no ekf_node diagnostics")
        status, values = next(((s, v) for s, v in reports() if at_rate(v)), reports()[-1])
        print(f"ekf_node diagnostics: level {ord(status.level)}, {status.message}")
        self.assertTrue(found, f"ekf_node never reported the drivers' rates {expected}: {values}")
        self.assertNotEqual(status.level, DiagnosticStatus.ERROR, status.message)
        self.assertGreater(int(values["imu.received"]), 0)
        # the estimates test_5 received are counted in a report
        self.assertTrue(
            wait_until(lambda: int(reports()[-1][1]["estimates_published"]) > 0, 10.0),
            f"ekf_node reports no estimates published: {reports()[-1][1]}",
        )

    def test_7_no_process_exited_while_running(self, proc_info):
        self.assertEqual(len(list(proc_info)), len(NODES))
        exited = [i.process_name for i in proc_info if isinstance(i, ProcessExited)]
        self.assertEqual(exited, [], "exited before the launch was stopped")


@launch_testing.post_shutdown_test()
class TestLiveShutdown(unittest.TestCase):
    def test_exit_codes(self, proc_info):
        """Every node ends with status 0 on launch's SIGINT (run_node returns 0 then)."""
        launch_testing.asserts.assertExitCodes(proc_info)
        self.assertEqual({name.rsplit("-", 1)[0] for name in proc_info.process_names()}, NODES)

    def test_no_traceback(self, proc_output):
        for io in proc_output:
            text = io.text.decode(errors="replace")
            self.assertNotIn("Traceback", text, f"{io.process_name}: {text}")
