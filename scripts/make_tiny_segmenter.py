"""Writes tests/data/tiny_segmenter.onnx: a 3-class "segmenter" for the tests.

Input "rgb" [N, 3, H, W] (pixel values 0..255, N/H/W dynamic); output "logits" [N, 3, H/2, W/2]:
a 1x1 convolution with identity weights followed by 2x2 average pooling, so the argmax is the
dominant colour channel (red -> class 0, green -> 1, blue -> 2) at half resolution, which also
exercises the resize back to the image size. Regenerate with:  python3 scripts/make_tiny_segmenter.py
(needs `pip install onnx`).
"""
import onnx
from onnx import TensorProto, helper

weights = helper.make_tensor("w", TensorProto.FLOAT, [3, 3, 1, 1], [1, 0, 0, 0, 1, 0, 0, 0, 1])
conv = helper.make_node("Conv", ["rgb", "w"], ["mixed"], kernel_shape=[1, 1])
pool = helper.make_node("AveragePool", ["mixed"], ["logits"], kernel_shape=[2, 2], strides=[2, 2])
graph = helper.make_graph(
    [conv, pool],
    "tiny_segmenter",
    [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, ["N", 3, "H", "W"])],
    [helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["N", 3, "h", "w"])],
    [weights],
)
model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], producer_name="semlook-tests")
model.ir_version = 8
onnx.checker.check_model(model)
onnx.save(model, "tests/data/tiny_segmenter.onnx")
print("wrote tests/data/tiny_segmenter.onnx")
