#!/usr/bin/env bash
# Build the colcon workspace ros2_ws/ (package psprm_ros, ament_python) with the project's venv.
#   bash scripts/build_ros2_ws.sh [BASE_DIR]      # default BASE_DIR: ros2_ws (build/, install/, log/ inside it)
# Afterwards (on a ROS 2 Jazzy machine): source <BASE_DIR>/install/setup.bash; ros2 run psprm_ros all_in_one ...
# The executables land in <BASE_DIR>/install/psprm_ros/lib/psprm_ros/.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
base="$(mkdir -p "${1:-$root/ros2_ws}" && cd "${1:-$root/ros2_ws}" && pwd)"
venv="${PSPRM_VENV:-$root/.venv}"
if [ -x "$venv/bin/colcon" ]; then colcon=("$venv/bin/colcon"); export PATH="$venv/bin:$PATH"; else colcon=(colcon); fi
cd "$base"
exec "${colcon[@]}" --log-base "$base/log" build --base-paths "$root/ros2_ws/src" \
  --build-base "$base/build" --install-base "$base/install" ${COLCON_ARGS:-}
