#!/usr/bin/env bash
# Start sim_robot: a kinematic simulation of the scene's robot behind the interfaces a real robot offers (its
# controllers' JointTrajectory topics and cmd_vel from the adapter config; /joint_states, /odom out).
#   bash scripts/run_sim_robot.sh [PARAMS_FILE] [ROS ARGS ...]     e.g. -p sim_robot:mocap_topic:=/mocap/stretch/pose
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
. "$root/scripts/ros_env.sh"  # $params (first argument), $py, PYTHONPATH, RMW_IMPLEMENTATION
exec "$py" -m psprm_ros.sim_robot --ros-args --params-file "$params" "$@"
