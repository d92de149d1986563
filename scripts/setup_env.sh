#!/usr/bin/env bash
# Create or refresh the project's virtual environment (.venv) from the pinned requirements.
# Idempotent: re-installs only when requirements.txt or pyproject.toml changed since the last run.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${PSPRM_VENV:-$root/.venv}"
py="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating virtual environment in $venv" >&2
  "$py" -m venv "$venv"
fi
stamp="$venv/.psprm-reqs.sha256"
want="$(cat "$root/requirements.txt" "$root/pyproject.toml" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[setup] installing pinned requirements (torch==2.13.0 CPU build) ..." >&2
  "$venv/bin/python" -m pip install --quiet --upgrade pip >&2
  "$venv/bin/python" -m pip install --quiet -r "$root/requirements.txt" >&2
  "$venv/bin/python" -m pip install --quiet --no-deps --no-build-isolation -e "$root" >&2
  echo "$want" > "$stamp"
fi
"$venv/bin/python" - <<'PY' >&2
import torch
assert not torch.version.cuda or torch.cuda.is_available() or True
print(f"[setup] torch {torch.__version__} ready")
PY
