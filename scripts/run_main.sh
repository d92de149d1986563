#!/usr/bin/env bash
# The main job: set up (or refresh) the environment and the planner's compiled kernels, then run psprm end to end
# on the embedded default scene in closed loop: the ROS 2 node suite (roadmap server, perception scorer, replan
# monitor, robot adapter, one process) and sim_robot (a simulated Stretch 2 behind its controller topic and cmd_vel)
# on `dynamic_person`, with the shipped motion-capture recording of a person turning side to side replayed until the
# robot rests at a goal; prints every plan and replan (triggers, latencies), the executed motion, the executed
# configurations in collision with the person and the oracle's verdict; writes out/ros_demo.png / out/ros_demo.json.
# The planning-only walk-through is `.venv/bin/psprm demo --scene home`.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/setup_env.sh"
bash "$root/scripts/warm_up_ros.sh"
cd "$root"
exec "$root/.venv/bin/python" -m psprm_ros.harness.demo --params config/ros/dynamic_person.yaml \
  --recording config/recordings/person_turning.csv --out "${PSPRM_OUT:-out}" "$@"
