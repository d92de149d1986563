"""Adapter for your own YOLO-style ONNX export (YOLOv5 or YOLOv8/v11 heads), run with onnxruntime.

Bring the file yourself (for instance ``yolo export model=yolov8n.pt format=onnx`` on a machine with internet); this
project never downloads weights. Supported output layouts (single output, batch 1):

* YOLOv8/v11: ``(1, 4 + C, N)`` -- rows ``cx, cy, w, h`` then ``C`` class scores;
* YOLOv5: ``(1, N, 5 + C)`` -- ``cx, cy, w, h, objectness`` then ``C`` class scores.

Coordinates are in input pixels of the letterboxed square input.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from .base import Detection, Detector, DetectorUnavailableError, nms, onnx_session
from .centernet import COCO80

log = logging.getLogger(__name__)


class OnnxYoloDetector(Detector):
    """YOLO ONNX file -> :class:`Detector`.

    Parameters
    ----------
    model_path : path
    class_names : sequence of str, optional
        Label per class index; defaults to the 80 COCO names.
    name : str
        Detector name used in threshold tables (default ``"onnx-yolo"``).
    min_score, iou : float
        Score cut and per-class NMS IoU.
    """

    def __init__(self, model_path, class_names: Optional[Sequence[str]] = None, name: str = "onnx-yolo",
                 min_score: float = 0.05, iou: float = 0.5, threads: int = 0):
        self.model_path = Path(model_path)
        if not self.model_path.is_file():
            raise DetectorUnavailableError(f"ONNX model not found: {self.model_path}")
        self.name = name
        self.class_names = tuple(class_names) if class_names else COCO80
        self.classes = frozenset(self.class_names)
        self.min_score, self.iou = float(min_score), float(iou)
        self._sess = onnx_session(self.model_path, threads=threads)
        inp = self._sess.get_inputs()[0]
        self._input = inp.name
        size = inp.shape[2] if len(inp.shape) == 4 and isinstance(inp.shape[2], int) else 640
        self.input_size = int(size)

    def detect(self, rgb: np.ndarray) -> List[Detection]:
        from PIL import Image

        img = np.asarray(rgb)[..., :3].astype(np.uint8)
        h, w = img.shape[:2]
        s = self.input_size / max(h, w)
        nh, nw = int(round(h * s)), int(round(w * s))
        canvas = np.full((self.input_size, self.input_size, 3), 114, np.uint8)
        top, left = (self.input_size - nh) // 2, (self.input_size - nw) // 2
        canvas[top:top + nh, left:left + nw] = np.asarray(Image.fromarray(img).resize((nw, nh), Image.BILINEAR))
        x = canvas.astype(np.float32).transpose(2, 0, 1)[None] / 255.0
        out = np.asarray(self._sess.run(None, {self._input: x})[0])[0]
        return self.decode(out, s, left, top, (w, h))

    def decode(self, out: np.ndarray, scale: float, left: float, top: float, image_wh) -> List[Detection]:
        """Turn one image's raw output into detections in original-image pixels."""
        c = len(self.class_names)
        if out.shape[0] == 4 + c:  # v8: (4 + C, N)
            boxes, cls_scores = out[:4].T, out[4:].T
        elif out.shape[-1] == 5 + c:  # v5: (N, 5 + C)
            boxes, cls_scores = out[:, :4], out[:, 5:] * out[:, 4:5]
        else:
            raise DetectorUnavailableError(f"unsupported YOLO output shape {out.shape} for {c} classes")
        cls = np.argmax(cls_scores, axis=1)
        score = cls_scores[np.arange(len(cls)), cls]
        keep = score >= self.min_score
        boxes, cls, score = boxes[keep], cls[keep], score[keep]
        xyxy = np.stack([boxes[:, 0] - boxes[:, 2] / 2, boxes[:, 1] - boxes[:, 3] / 2,
                         boxes[:, 0] + boxes[:, 2] / 2, boxes[:, 1] + boxes[:, 3] / 2], axis=1)
        xyxy = (xyxy - np.array([left, top, left, top])) / scale
        w, h = image_wh
        xyxy[:, 0::2] = np.clip(xyxy[:, 0::2], 0, w)
        xyxy[:, 1::2] = np.clip(xyxy[:, 1::2], 0, h)
        dets: List[Detection] = []
        for k in np.unique(cls):
            idx = np.nonzero(cls == k)[0]
            for j in nms(xyxy[idx], score[idx], self.iou):
                i = idx[j]
                dets.append(Detection(box_xyxy=xyxy[i], score=float(score[i]), label=self.class_names[k]))
        dets.sort(key=lambda d: -d.score)
        return dets
