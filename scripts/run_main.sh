#!/usr/bin/env bash
# The main job: set up (or refresh) the environment, then run psprm end to end on the embedded default scene.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/setup_env.sh"
cd "$root"
exec "$root/.venv/bin/psprm" demo --scene "${PSPRM_SCENE:-home}" --out "${PSPRM_OUT:-out}" "$@"
