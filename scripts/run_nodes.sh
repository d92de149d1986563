#!/usr/bin/env bash
# Start the psprm node suite as four processes: roadmap_server, perception_scorer, replan_monitor, robot_adapter.
#   bash scripts/run_nodes.sh [PARAMS_FILE] [ROS ARGS ...]
# Same parameters as run_all_in_one.sh (overrides: -p NODE:name:=value). Ctrl-C / SIGTERM stops all of them (the adapter stops the robot); if one node exits, the others are stopped
# and the script exits with that node's status.
set -uo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
. "$root/scripts/ros_env.sh"  # $params (first argument), $py, PYTHONPATH, RMW_IMPLEMENTATION
pids=()
stop() { kill -TERM "${pids[@]}" 2>/dev/null; wait "${pids[@]}" 2>/dev/null; }
trap 'stop; exit 0' INT TERM
for node in roadmap_server perception_scorer replan_monitor robot_adapter; do
  "$py" -m "psprm_ros.$node" --ros-args --params-file "$params" "$@" &
  pids+=($!)
done
wait -n "${pids[@]}"
status=$?
echo "run_nodes.sh: a node exited (status $status); stopping the others" >&2
stop
exit "$status"
