#!/usr/bin/env bash
# The device check on a bare CUDA machine (no network; a Python with a CUDA torch, numba, numpy, scipy and pyyaml,
# nothing else of requirements.txt): judged against the references carried in the repository
# (psprm_core/data/device_check/references.npz, written by `python -m psprm_core.evaluation.device_check --record`
# in the full environment), with no .venv and no install: PYTHONPATH is this repository.
#   bash scripts/check_device_bare.sh                 # cuda
#   bash scripts/check_device_bare.sh cuda:1
#   PYTHON=.venv/bin/python bash scripts/check_device_bare.sh cpu --torch-path   # the same check here
# Further arguments go to the check (--configs/--queries/--replans N: the first N of the references). The module runs
# through scripts/bare_run.py, which makes the requirements such a machine lacks unimportable (pybullet, ompl, rclpy,
# ray, toppra, trimesh, ...), here as there. Prints one JSON line (CPU and device timings side by side); exit 0 =
# every check passed, or no CUDA here ("checked": false), 1 = a check failed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="${PYTHON:-python3}"
device="${1:-cuda}"
shift || true
cd "$root"
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
exec "$py" "$root/scripts/bare_run.py" -m psprm_core.evaluation.device_check --device "$device" \
  --references "$root/psprm_core/data/device_check/references.npz" "$@"
