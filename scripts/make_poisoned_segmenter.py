"""Writes a poisoned segmenter: an ONNX graph with the default segmenter's interface (one input, RGB
[N, 3, H, W]; one output, logits of the 19 Cityscapes classes at half the resolution) that labels every
pixel "road" whatever the image. Installed in place of the real one, it makes any test that quietly
reads the installed segmenter see a world without edges (issue 56: scripts/poisoned-tests.sh runs the
Python suite so). Needs `onnx` (the exporters' venv has it):
    .venv-export/bin/python scripts/make_poisoned_segmenter.py OUT.onnx
"""
import sys

import onnx
from onnx import TensorProto, helper

CLASSES = 19
weights = helper.make_tensor("w", TensorProto.FLOAT, [CLASSES, 3, 1, 1], [0.0] * (CLASSES * 3))
bias = helper.make_tensor("b", TensorProto.FLOAT, [CLASSES], [1.0] + [0.0] * (CLASSES - 1))
conv = helper.make_node("Conv", ["rgb", "w", "b"], ["mixed"], kernel_shape=[1, 1])
pool = helper.make_node("AveragePool", ["mixed"], ["logits"], kernel_shape=[2, 2], strides=[2, 2])
graph = helper.make_graph(
    [conv, pool],
    "poisoned_segmenter",
    [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, ["N", 3, "H", "W"])],
    [helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["N", CLASSES, "h", "w"])],
    [weights, bias],
)
model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], producer_name="semlook-tests")
model.ir_version = 8
onnx.checker.check_model(model)
onnx.save(model, sys.argv[1])
print(f"wrote {sys.argv[1]}: every pixel class 0 (road)")
