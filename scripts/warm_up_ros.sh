#!/usr/bin/env bash
# Set-up step of the ROS main job: compile the planner's numba kernels (A*, hop BFS, the compiled verification
# paths) into their on-disk cache with a small throw-away roadmap (200 nodes, not saved) and one replan, as the Docker
# image does at build time (python -m psprm_ros.warm_up). The first run on a fresh checkout takes about a minute;
# once cached it takes a few seconds. No roadmap is cached: the nodes still build (or load) their own.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="${PSPRM_PYTHON:-$root/.venv/bin/python}"
t0=$SECONDS
cd "$root"
PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}" "$py" -m psprm_ros.warm_up >/dev/null
echo "[setup] planner kernels compiled or loaded from their cache in $((SECONDS - t0)) s" >&2
