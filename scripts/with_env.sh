#!/usr/bin/env bash
# Runs a command with the project venv active and ROS 2 confined to loopback.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
export VIRTUAL_ENV="$root/.venv" PATH="$root/.venv/bin:$PATH"
export AMENT_PREFIX_PATH="$root/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_LOG_DIR=${ROS_LOG_DIR:-$root/.ros_log}
export RCUTILS_COLORIZED_OUTPUT=0
exec "$@"
