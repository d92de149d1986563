# Shared set-up of run_all_in_one.sh and run_nodes.sh, sourced with no arguments after `root` is set: takes the
# optional PARAMS_FILE from the caller's arguments into $params (default config/ros/dynamic_person.yaml; the rest stay
# in "$@"), picks the project's Python into $py and exports PYTHONPATH and RMW_IMPLEMENTATION.
params="${1:-$root/config/ros/dynamic_person.yaml}"
[ $# -gt 0 ] && shift
[ -f "$params" ] || { echo "$(basename "$0"): params file not found: $params" >&2; exit 2; }
py="${PSPRM_PYTHON:-$root/.venv/bin/python}"
[ -x "$py" ] || py=python3
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
