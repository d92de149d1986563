"""The detector interface: anything that turns an RGB image into labelled, scored boxes.

Implement :class:`Detector` (or just match its shape: ``name``, ``classes`` and ``detect``) to plug your own model into
the :class:`~psprm_core.perception.oracle.Oracle`.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import FrozenSet, List

import numpy as np

from ...errors import PsprmError


class DetectorUnavailableError(PsprmError):
    """A detector's model file is missing or its runtime package is not installed."""


@dataclass(frozen=True)
class Detection:
    """One detected object.

    Attributes
    ----------
    box_xyxy : (4,) ndarray
        ``[x1, y1, x2, y2]`` in pixels of the input image (x right, y down).
    score : float
        Detector confidence in [0, 1].
    label : str
        Class name (``"face"``, or a COCO class such as ``"cup"``).
    """

    box_xyxy: np.ndarray
    score: float
    label: str


class Detector(abc.ABC):
    """Abstract detector.

    Attributes
    ----------
    name : str
        Short identifier (``"centerface"``), used in threshold tables and reports.
    classes : frozenset of str
        Labels this detector can emit.
    """

    name: str = "detector"
    classes: FrozenSet[str] = frozenset()

    @abc.abstractmethod
    def detect(self, rgb: np.ndarray) -> List[Detection]:
        """Detect objects in an ``(H, W, 3)`` uint8 RGB image; boxes are in that image's pixel coordinates."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, {len(self.classes)} classes)"


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression, highest score first."""
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    order = np.argsort(-np.asarray(scores, float))
    keep = []
    area = np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1], 0, None)
    while order.size:
        i = order[0]
        keep.append(i)
        rest = order[1:]
        ix1 = np.maximum(boxes[i, 0], boxes[rest, 0])
        iy1 = np.maximum(boxes[i, 1], boxes[rest, 1])
        ix2 = np.minimum(boxes[i, 2], boxes[rest, 2])
        iy2 = np.minimum(boxes[i, 3], boxes[rest, 3])
        inter = np.clip(ix2 - ix1, 0, None) * np.clip(iy2 - iy1, 0, None)
        iou = inter / np.maximum(area[i] + area[rest] - inter, 1e-9)
        order = rest[iou < iou_threshold]
    return np.array(keep, dtype=int)


def onnx_session(path, threads: int = 0):
    """An onnxruntime CPU inference session with warnings silenced.

    Parameters
    ----------
    path : str, Path or bytes
        Model file, or a serialized model.
    threads : int
        Intra-op threads (0 = onnxruntime's default, all cores).
    """
    try:
        import onnxruntime as ort
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DetectorUnavailableError("onnxruntime is not installed: run scripts/install_detectors.sh") from exc
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    if threads:
        opts.intra_op_num_threads = int(threads)
    model = path if isinstance(path, (bytes, bytearray)) else str(path)
    return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
