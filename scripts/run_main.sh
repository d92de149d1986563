#!/usr/bin/env bash
# The main job: set up (or refresh) the environment, then run psprm end to end on the embedded default scene:
# the ROS 2 node suite (roadmap server, perception scorer, replan monitor, all in one process) on `dynamic_person`,
# driven by the shipped motion-capture recording of a person turning side to side; prints every plan and replan
# (triggers, latencies, predicted and oracle scores) and writes out/ros_demo.png / out/ros_demo.json.
# The planning-only walk-through is `.venv/bin/psprm demo --scene home`.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/setup_env.sh"
cd "$root"
exec "$root/.venv/bin/python" -m psprm_ros.demo --params config/ros/dynamic_person.yaml \
  --recording config/recordings/person_turning.csv --out "${PSPRM_OUT:-out}" "$@"
