# Prototype (sweep 16): EfficientNet-Lite feature maps of the three real dev sets' images, pooled (GeM p = 3,
# average, max) into OUT/TAG.npz. Usage: features.py MODEL.onnx LONG_SIDE TAG (onnxruntime, numpy, onnx, pillow:
# .venv-export has them).
import sys, os, numpy as np, onnx, onnxruntime as ort
from PIL import Image
model, size, tag = sys.argv[1], int(sys.argv[2]), sys.argv[3]
m = onnx.load(model)
gap = [n for n in m.graph.node if n.op_type == 'GlobalAveragePool'][0]
head = gap.input[0]
# also the last 320-channel block output: the input of the head conv's chain
m.graph.output.append(onnx.helper.make_tensor_value_info(head, onnx.TensorProto.FLOAT, None))
so = ort.SessionOptions(); so.intra_op_num_threads = 2
sess = ort.InferenceSession(m.SerializeToString(), so)
R = os.environ.get('REAL_VPR', '../shared/data/real-vpr')
OUT = os.environ.get('OUT', 'embedding-prototype-out')
def prep(path):
    im = Image.open(path).convert('RGB'); w, h = im.size; s = size / max(w, h)
    im = im.resize((max(32, round(w * s)), max(32, round(h * s))), Image.BICUBIC)
    a = (np.asarray(im, np.float32) - 127.0) / 128.0
    return a.transpose(2, 0, 1)[None].astype(np.float32)
out = {}
for name in ['gardenspoint-day-night-mini', 'nordland-spring-winter', 'landmarks-multiview-dev']:
    for part in ['ref', 'query']:
        files = sorted(os.listdir(f'{R}/{name}/{part}'))
        gem, avg, mx = [], [], []
        for f in files:
            fm = sess.run([head], {'input': prep(f'{R}/{name}/{part}/{f}')})[0][0]  # C,h,w
            x = fm.reshape(fm.shape[0], -1)
            avg.append(x.mean(1)); mx.append(x.max(1)); gem.append(np.cbrt(np.mean(np.maximum(x, 1e-6) ** 3, 1)))
        out[f'{name}/{part}/files'] = np.array(files)
        for k, v in [('gem', gem), ('avg', avg), ('max', mx)]:
            out[f'{name}/{part}/{k}'] = np.stack(v)
        print(name, part, len(files), flush=True)
os.makedirs(OUT, exist_ok=True)
np.savez(f'{OUT}/{tag}.npz', **out)
