#!/usr/bin/env bash
# Start the psprm node suite in ONE process (roadmap_server + perception_scorer + replan_monitor on a
# MultiThreadedExecutor): the lowest pose-to-trajectory latency.
#   bash scripts/run_all_in_one.sh [PARAMS_FILE] [ROS ARGS ...]
#   e.g. bash scripts/run_all_in_one.sh config/ros/dynamic_person.yaml -p roadmap_server:roadmap.n_nodes:=1000
# PARAMS_FILE defaults to config/ros/dynamic_person.yaml; extra arguments go after --ros-args (-r from:=to,
# --log-level debug, -p NODE:name:=value -- give the node name: a plain -p name:=value does not override a value
# the params file sets in a node's own section). Stops cleanly on Ctrl-C / SIGTERM.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
. "$root/scripts/ros_env.sh"  # $params (first argument), $py, PYTHONPATH, RMW_IMPLEMENTATION
exec "$py" -m psprm_ros.all_in_one --ros-args --params-file "$params" "$@"
