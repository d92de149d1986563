#!/usr/bin/env bash
# Check the tensor pipeline (FK, collision, neural scoring with occlusion, a PS-PRM build and query) on a torch
# device against pybullet and the CPU: `bash scripts/check_device.sh` (cuda), `bash scripts/check_device.sh cuda:1`,
# `bash scripts/check_device.sh cpu --torch-path` (the torch path on this CPU, compiled kernels off).
# Prints one JSON line (CPU and device timings side by side); exit 0 = every check passed, or no CUDA here (it says
# so: "checked": false), 1 = a check failed.
# The project's environment carries a CPU build of torch; on a CUDA machine install the CUDA build of the same torch
# version into .venv first (the requirements pin the version, the build is the machine's choice). A CUDA machine
# without this environment runs scripts/check_device_bare.sh instead (references carried in the repository).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
[ -x "$root/.venv/bin/python" ] || bash "$root/scripts/setup_env.sh"
device="${1:-cuda}"
shift || true
cd "$root"
exec "$root/.venv/bin/python" -m psprm_core.evaluation.device_check --device "$device" "$@"
