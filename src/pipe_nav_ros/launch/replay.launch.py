"""Replay a recorded bag through ekf_node on simulated time, optionally recording the output.

    ros2 launch pipe_nav_ros replay.launch.py bag:=run.mcap
    ros2 launch pipe_nav_ros replay.launch.py bag:=run.mcap record:=true output:=run_ekf

``ros2 bag play <bag> --clock`` publishes the input topics and /clock; ekf_node runs with
use_sim_time:=true; the sensor topics are played and subscribed reliable (config/player_qos.yaml,
sensor_qos_reliable), so a node that falls behind makes the player wait and loses nothing; with
record:=true, ``ros2 bag record -s mcap -o <output>`` records
/pipe_nav/odometry, /pipe_nav/datum and /diagnostics into the rosbag2 directory <output>
(default: <bag name>_ekf beside the bag). The bag plays once ekf_node says it is ready (its
numeric kernels loaded: seconds, minutes on a fresh install) and the recorder has subscribed to
/pipe_nav/odometry, after ``delay`` more seconds, so the estimator sees the bag from its first
message on. When the bag has played, ekf_node's ~/finish service flushes the last estimates
and, with shutdown_when_done:=true, the launch ends (closing the recording); it also ends when
ekf_node does. The ROS-free equivalent is ``pipe-nav replay IN.mcap --out OUT.mcap``.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    ExecuteProcess,
    LogInfo,
    OpaqueFunction,
    RegisterEventHandler,
    Shutdown,
    TimerAction,
)
from launch.event_handlers import OnProcessExit, OnProcessIO
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "pipe_nav_ros"
INPUT_TOPICS = ["/imu/data", "/odom/wheel", "/imu/mag", "/markers"]
RECORDED_TOPICS = ["/pipe_nav/odometry", "/pipe_nav/datum", "/diagnostics"]
EKF_READY = b"ekf_node ready"  # ekf_node's log line once it takes data
RECORDER_READY = b"Subscribed to topic '/pipe_nav/odometry'"  # ros2 bag record's log line


def _arg(context, name):
    return LaunchConfiguration(name).perform(context)


def _truthy(text):
    return text.strip().lower() in ("1", "true", "yes", "on")


def default_output(bag):
    """<bag name without .mcap>_ekf beside the bag."""
    bag = os.path.abspath(bag.rstrip(os.sep))
    stem = os.path.basename(bag)
    if stem.endswith(".mcap"):
        stem = stem[: -len(".mcap")]
    return os.path.join(os.path.dirname(bag), stem + "_ekf")


def _actions(context):
    bag = _arg(context, "bag")
    if not bag:
        raise RuntimeError("replay.launch.py needs bag:=<input .mcap file or bag directory>")
    delay = float(_arg(context, "delay"))
    play_cmd = [
        "ros2",
        "bag",
        "play",
        bag,
        "--clock",
        "--rate",
        _arg(context, "rate"),
        "--disable-keyboard-controls",
    ]
    if delay > 0:
        play_cmd += ["--delay", str(delay)]
    play_cmd += ["--qos-profile-overrides-path", _arg(context, "player_qos")]
    play_cmd += ["--topics"] + INPUT_TOPICS
    play = ExecuteProcess(cmd=play_cmd, name="bag_play", output="screen")

    ekf = Node(
        package=PACKAGE,
        executable="ekf_node",
        name="ekf_node",
        output="screen",
        parameters=[
            _arg(context, "ekf_params"),
            {
                "use_sim_time": True,
                "publish_tf": _truthy(_arg(context, "publish_tf")),
                "sensor_qos_reliable": True,
            },
        ],
        on_exit=Shutdown(reason="ekf_node exited"),
    )
    # the bag plays once every process in ``waiting`` has logged its ready line
    waiting = {"ekf_node": (ekf, EKF_READY)}
    actions = []
    if _truthy(_arg(context, "record")):
        output = _arg(context, "output") or default_output(bag)
        if os.path.exists(output):
            raise RuntimeError(f"output {output} already exists; choose another output:=")
        record = ExecuteProcess(
            cmd=["ros2", "bag", "record", "-s", "mcap", "-o", output]
            + ["--qos-profile-overrides-path", _arg(context, "recorder_qos")]
            + RECORDED_TOPICS,
            name="bag_record",
            output="screen",
        )
        waiting["bag_record"] = (record, RECORDER_READY)
        actions.append(LogInfo(msg=f"recording {' '.join(RECORDED_TOPICS)} into {output}"))

    def when_ready(name, marker):
        def on_output(event):
            if name not in waiting or marker not in event.text:
                return None
            del waiting[name]
            if waiting:
                return None
            return [LogInfo(msg=f"ready: playing {bag}"), play]

        return on_output

    for name, (action, marker) in list(waiting.items()):
        handler = when_ready(name, marker)
        actions.append(
            RegisterEventHandler(
                OnProcessIO(target_action=action, on_stdout=handler, on_stderr=handler)
            )
        )
    actions += [process for process, _ in waiting.values()]
    finish = ExecuteProcess(
        cmd=["ros2", "service", "call", "/ekf_node/finish", "std_srvs/srv/Trigger"],
        name="ekf_finish",
        output="screen",
    )
    # handlers before the processes they watch
    actions.append(
        RegisterEventHandler(
            OnProcessExit(
                target_action=play,
                on_exit=[LogInfo(msg="bag played; flushing ekf_node"), finish],
            )
        )
    )
    if _truthy(_arg(context, "shutdown_when_done")):
        actions.append(
            RegisterEventHandler(
                OnProcessExit(
                    target_action=finish,
                    on_exit=[TimerAction(period=2.0, actions=[Shutdown(reason="bag replayed")])],
                )
            )
        )
    return actions  # play: started by the ready handlers


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    arguments = [
        ("bag", "", "input bag: .mcap file or rosbag2 directory (required)"),
        ("record", "false", "record the output topics with ros2 bag record"),
        ("output", "", "record: output bag directory (default <bag name>_ekf)"),
        ("rate", "1.0", "playback rate factor"),
        (
            "delay",
            "1.0",
            "seconds from ekf_node (and the recorder) being ready to the start of the playback",
        ),
        ("publish_tf", "true", "ekf_node broadcasts TF map -> base_link"),
        ("shutdown_when_done", "true", "end the launch once the bag has played and ekf flushed"),
        ("ekf_params", os.path.join(share, "config", "ekf.yaml"), "ekf_node parameter file"),
        (
            "player_qos",
            os.path.join(share, "config", "player_qos.yaml"),
            "the player's QoS overrides (the sensors reliable: nothing lost behind a backlog)",
        ),
        (
            "recorder_qos",
            os.path.join(share, "config", "recorder_qos.yaml"),
            "record: the recorder's QoS overrides (deep enough for ekf_node's bursts)",
        ),
    ]
    return LaunchDescription(
        [DeclareLaunchArgument(n, default_value=d, description=h) for n, d, h in arguments]
        + [OpaqueFunction(function=_actions)]
    )
