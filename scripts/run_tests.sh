#!/usr/bin/env bash
# The test suite: set up (or refresh) the environment, then run pytest. Exits non-zero when a test fails
# (and when no test ran at all).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/setup_env.sh"
cd "$root"
exec "$root/.venv/bin/python" -m pytest -q -p no:cacheprovider "$@"
