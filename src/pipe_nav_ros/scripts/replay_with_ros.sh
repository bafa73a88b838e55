#!/usr/bin/env bash
# Play a recorded bag into ekf_node (simulated time) and record its output to a new bag.
#
#   replay_with_ros.sh IN_BAG OUT_DIR [RATE] [PARAMS]
#
# IN_BAG: .mcap file or rosbag2 directory with /imu/data, /odom/wheel, /imu/mag, /markers.
# OUT_DIR: new rosbag2 directory (MCAP storage) that receives /pipe_nav/odometry,
#          /pipe_nav/datum and /diagnostics; it must not exist yet.
# RATE: playback speed factor (default 1.0).
# PARAMS: ekf_node parameter file in the config/ekf.yaml format (default: that file).
#
# Needs a sourced ROS 2 Jazzy environment with this workspace (source install/setup.bash).
# It runs `ros2 launch pipe_nav_ros replay.launch.py ... record:=true` and returns when the bag
# has played and ekf_node has flushed its last estimates. Without ROS, the same estimator runs
# with:  pipe-nav replay IN.mcap --out OUT.mcap
set -euo pipefail

usage() {
  sed -n '2,15p' "$0" | sed 's/^# \{0,1\}//'
  exit "${1:-2}"
}

if [ "${1:-}" = "-h" ] || [ "${1:-}" = "--help" ]; then
  usage 0
fi
if [ $# -lt 2 ] || [ $# -gt 4 ]; then
  usage 2
fi

in_bag=$1
out_dir=$2
rate=${3:-1.0}
params=${4:-}
case "$rate" in
  ''|*[!0-9.]*|*.*.*) echo "replay_with_ros.sh: RATE must be a positive number, not '$rate'" >&2; exit 2 ;;
esac

if ! command -v ros2 >/dev/null 2>&1; then
  echo "replay_with_ros.sh: ros2 not found; source /opt/ros/jazzy/setup.bash and install/setup.bash" >&2
  exit 1
fi
if [ ! -e "$in_bag" ]; then
  echo "replay_with_ros.sh: input bag $in_bag does not exist" >&2
  exit 1
fi
if [ -e "$out_dir" ]; then
  echo "replay_with_ros.sh: output $out_dir already exists (ros2 bag record needs a new directory)" >&2
  exit 1
fi

if [ -n "$params" ] && [ ! -f "$params" ]; then
  echo "replay_with_ros.sh: parameter file $params does not exist" >&2
  exit 1
fi
extra=()
if [ -n "$params" ]; then
  extra=(ekf_params:="$params")
fi
exec ros2 launch pipe_nav_ros replay.launch.py \
  bag:="$in_bag" output:="$out_dir" record:=true rate:="$rate" shutdown_when_done:=true "${extra[@]}"
