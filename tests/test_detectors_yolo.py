"""The generic YOLO ONNX adapter, on a tiny synthetic ONNX graph (no real weights needed)."""

from __future__ import annotations

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from psprm_core.perception.detectors import make_detector  # noqa: E402


def _constant_yolo(path, out: np.ndarray, size: int = 64) -> None:
    """ONNX graph: images (1, 3, size, size) -> constant ``out`` (the input is used, multiplied by zero)."""
    const = numpy_helper.from_array(out.astype(np.float32), "const")
    zero = numpy_helper.from_array(np.zeros((), np.float32), "zero")
    nodes = [
        helper.make_node("ReduceSum", ["images"], ["s"], keepdims=0),
        helper.make_node("Mul", ["s", "zero"], ["z"]),
        helper.make_node("Add", ["const", "z"], ["output0"]),
    ]
    graph = helper.make_graph(nodes, "yolo", [helper.make_tensor_value_info("images", TensorProto.FLOAT,
                                                                            [1, 3, size, size])],
                              [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(out.shape))],
                              initializer=[const, zero])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(path))


def test_yolov8_layout(tmp_path):
    out = np.zeros((1, 84, 3), np.float32)
    out[0, :4, 0] = [32, 32, 16, 8]  # cx, cy, w, h in the 64-px letterboxed input
    out[0, 4 + 41, 0] = 0.8  # cup
    out[0, :4, 1] = [33, 32, 16, 8]
    out[0, 4 + 41, 1] = 0.6  # duplicate, suppressed by NMS
    out[0, 4 + 0, 2] = 0.01  # below min_score
    path = tmp_path / "v8.onnx"
    _constant_yolo(path, out)
    det = make_detector(f"onnx-yolo:{path}")
    dets = det.detect(np.zeros((48, 64, 3), np.uint8))  # letterboxed: scale 1, 8 px top padding
    assert len(dets) == 1 and dets[0].label == "cup" and dets[0].score == pytest.approx(0.8)
    np.testing.assert_allclose(dets[0].box_xyxy, [24, 20, 40, 28], atol=1e-4)


def test_yolov5_layout(tmp_path):
    out = np.zeros((1, 2, 85), np.float32)
    out[0, 0, :5] = [32, 32, 20, 20, 0.9]
    out[0, 0, 5 + 62] = 0.5  # tv, score = 0.9 * 0.5
    path = tmp_path / "v5.onnx"
    _constant_yolo(path, out)
    dets = make_detector(f"onnx-yolo:{path}", min_score=0.1).detect(np.zeros((64, 64, 3), np.uint8))
    assert [d.label for d in dets] == ["tv"] and dets[0].score == pytest.approx(0.45)
