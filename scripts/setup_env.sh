#!/usr/bin/env bash
# Create or refresh the project's virtual environment (.venv): pinned requirements, psprm itself (editable) and the
# perception oracle's detector models (scripts/install_detectors.sh, cached under ~/.cache/psprm).
# Idempotent: re-installs only when requirements.txt, pyproject.toml or the detector installer changed. Then the ROS 2
# interfaces that are not on PyPI (control_msgs, tf2_msgs: scripts/build_interfaces.sh) are generated into the venv;
# that script keeps its own stamp and rebuilds only when their definitions, itself or its pins changed.
set -euo pipefail
exec </dev/null
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${PSPRM_VENV:-$root/.venv}"
py="${PYTHON:-python3}"
quiet_pip() { grep -v -e "is ignored: it is neither a file nor a directory" -e "^$" >&2 || true; }
if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating virtual environment in $venv" >&2
  "$py" -m venv "$venv"
fi
stamp="$venv/.psprm-reqs.sha256"
want="$(cat "$root/requirements.txt" "$root/pyproject.toml" "$root/scripts/install_detectors.sh" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[setup] installing pinned requirements (torch==2.13.0, CPU build) ..." >&2
  "$venv/bin/python" -m pip install --quiet --upgrade pip 2>&1 | quiet_pip
  "$venv/bin/python" -m pip install --quiet -r "$root/requirements.txt" 2>&1 | quiet_pip
  # The editable install builds with the venv's own setuptools (no build isolation): >= 77 reads the SPDX license
  # string of pyproject.toml. Its notice about editable installs is informational and filtered out.
  "$venv/bin/python" -m pip install --quiet "setuptools>=77" 2>&1 | quiet_pip
  echo "[setup] installing psprm (editable) ..." >&2
  PYTHONWARNINGS="ignore:Editable installation" \
    "$venv/bin/python" -m pip install --quiet --no-deps --no-build-isolation -e "$root" 2>&1 | quiet_pip
  "$venv/bin/python" -c "import torch, psprm_core; assert torch.__version__.startswith('2.13.0')" 
  echo "[setup] installing detector models (first run converts CenterNet once; cached afterwards) ..." >&2
  bash "$root/scripts/install_detectors.sh" "$venv/bin/python" >&2
  echo "$want" > "$stamp"
fi
# control_msgs/tf2_msgs from their definitions in ros2_ws/interfaces/ (a no-op in a fraction of a second when built)
bash "$root/scripts/build_interfaces.sh" "$venv/bin/python"
