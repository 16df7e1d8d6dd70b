#!/usr/bin/env python3
"""Convert the authors' ESPNetv2 (s = 2.0) Cityscapes checkpoint into an ONNX segmentation model.

    python export_segmenter.py CHECKPOINT.pth OUT.onnx [--check REFERENCE.onnx --frames DIR]

The network is ESPNetv2 (Mehta, Rastegari, Shapiro, Hajishirzi, "ESPNetv2: A Light-weight, Power Efficient,
and General Purpose Convolutional Neural Network", CVPR 2019) in the segmentation form of the authors' code
(github.com/sacmehta/EdgeNets, MIT licence, `model/segmentation/espnetv2.py`): the EESPNet encoder without its
level-5 and classifier, then a bottom-up decoder of efficient pyramid-pooling blocks. The classes below are
written for this exporter; their module and parameter names follow the checkpoint (`base_net.*`,
`bu_dec_l1..l4`, `merge_enc_dec_l2..l4`, `bu_br_l2..l4`) so the state dict loads with strict=True.

The exported graph:
  input  `rgb`    float32 [1, 3, H, W], RGB 0..255; the graph divides by 255 and applies the ImageNet
                  mean/std, as the authors' data pipeline does;
  output `logits` float32 [1, 20, H, W]; argmax = Cityscapes train id 0..18, channel 19 = background.
                  The decoder ends at H/2 x W/2; the graph upsamples bilinearly (align_corners=True) to H x W.
H and W are dynamic, multiples of 16 (at least 48, see EfficientPyrPool). The pyramid-pooling blocks use
adaptive average pooling whose windows depend on the input size; `adaptive_avg_pool` writes it with ops whose
window bounds are computed from the (symbolic) sizes, and torch.export (strict, H = 16 h16, W = 16 w16) keeps
the sizes symbolic, so one graph serves every size. After writing the file the script runs it with onnxruntime
at several sizes against the PyTorch model to prove that. The export is byte-deterministic for a given
torch/onnxscript/onnx version (node metadata is dropped, serialisation is deterministic).

With --check REFERENCE.onnx --frames DIR it also runs both graphs on the frames in DIR (resized to 1024x512,
640x480 and 512x256) and prints the max |logit difference| and the argmax agreement per size; it exits 1 if the
logits differ by more than 1e-3 or the argmax differs at any pixel.

Needs the packages in requirements-export-torch.txt (torch, onnxscript, and requirements-export.txt: onnx, onnxruntime, numpy, pillow).
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

# --------------------------------------------------------------------------------------------------------------
# Configuration of the s = 2.0 model (EdgeNets `model/classification/espnetv2_config.py`, segmentation head of
# `model/segmentation/espnetv2.py` with dataset 'city').
# --------------------------------------------------------------------------------------------------------------
ENC_CHANNELS = (32, 128, 256, 512)  # outputs of level1, level2_0, level3, level4 at s = 2.0
ENC_REPEATS = (3, 7)                # EESP blocks after the down-samplers of level 3 and level 4
RECEPTIVE_LIMITS = (13, 11, 9, 7)   # largest effective 3x3-dilated kernel per spatial level (level2..level5)
BRANCHES = 4                        # parallel dilated branches in every EESP block
REINF_CHANNELS = 3                  # width of the input-reinforcement path (the RGB image)
NUM_CLASSES = 20                    # 19 Cityscapes train ids + background
DEC_BASE = 16                       # decoder width for 'city'
DEC_CHANNELS = (4 * DEC_BASE, 3 * DEC_BASE, 2 * DEC_BASE, NUM_CLASSES)
PYR_PROJ = min(NUM_CLASSES // 2, DEC_BASE)  # 10 channels inside the pyramid-pooling blocks
# Pyramid scales as exact fractions (num, den), largest first: 2.0, 1.5, 1.0, 0.5, 0.1.
PYR_SCALES = ((2, 1), (3, 2), (1, 1), (1, 2), (1, 10))
PYR_MIN_SIZE = 5                    # the authors never pool or resize a branch below 5x5

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CHECKPOINT_SHA256 = "a72d59699801c7ce8e8b89a53af9097eaaa60dc12180ecde86fd700ba1222fe8"
CHECKPOINT_TENSORS = 526
OPSET = 18

DOC_STRING = (
    "ESPNetv2 s=2.0 Cityscapes semantic segmentation (Mehta et al., CVPR 2019), weights "
    "espnetv2_s_2.0_city_1024x512.pth from github.com/sacmehta/EdgeNets (MIT licence, Copyright (c) 2021 "
    "Sachin Mehta), converted by semlook python/tools/export_segmenter.py. Input rgb float32 [1,3,H,W] RGB "
    "0..255 (/255 and ImageNet mean/std inside the graph), H,W multiples of 16; output logits float32 "
    "[1,20,H,W], argmax = Cityscapes train id (19 = background)."
)


def ceil_scaled(size, num: int, den: int):
    """ceil(size * num / den) in integer arithmetic, so it stays symbolic under torch.export.

    The authors write `int(math.ceil(size * scale))` with a float scale; for the scales used here the two agree
    for every size (checked for 1..8192 in `_check_ceil_formula`)."""
    return (size * num + den - 1) // den


def _check_ceil_formula() -> None:
    for num, den in PYR_SCALES:
        scale = num / den
        for size in range(1, 8193):
            assert ceil_scaled(size, num, den) == int(math.ceil(size * scale)), (size, num, den)


# --------------------------------------------------------------------------------------------------------------
# Building blocks. Two naming families exist in the checkpoint: the encoder uses `conv/bn/act` attributes
# (EdgeNets `nn_layers/espnet_utils.py`), the decoder uses a Sequential named `cbr` or `br`
# (EdgeNets `nn_layers/cnn_utils.py`). Convolutions carry no bias (except the classifier 1x1); BatchNorm eps is 1e-5.
# --------------------------------------------------------------------------------------------------------------
class ConvBNAct(nn.Module):
    """Conv (same padding) -> BatchNorm -> PReLU, attribute names conv/bn/act (authors' espnet_utils.CBR)."""

    def __init__(self, cin: int, cout: int, k: int, stride: int = 1, groups: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, k, stride=stride, padding=(k - 1) // 2, groups=groups, bias=False)
        self.bn = nn.BatchNorm2d(cout)
        self.act = nn.PReLU(cout)

    def forward(self, x):
        return self.act(self.bn(self.conv(x)))


class ConvBN(nn.Module):
    """Conv (same padding) -> BatchNorm, no activation (authors' espnet_utils.CB)."""

    def __init__(self, cin: int, cout: int, k: int, stride: int = 1, groups: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, k, stride=stride, padding=(k - 1) // 2, groups=groups, bias=False)
        self.bn = nn.BatchNorm2d(cout)

    def forward(self, x):
        return self.bn(self.conv(x))


class BNAct(nn.Module):
    """BatchNorm -> PReLU, attribute names bn/act (authors' espnet_utils.BR)."""

    def __init__(self, ch: int):
        super().__init__()
        self.bn = nn.BatchNorm2d(ch)
        self.act = nn.PReLU(ch)

    def forward(self, x):
        return self.act(self.bn(x))


class DilatedDWConv(nn.Module):
    """Depth-wise 3x3 convolution with dilation d and padding d, no BN (authors' espnet_utils.CDilated)."""

    def __init__(self, ch: int, stride: int, dilation: int):
        super().__init__()
        self.conv = nn.Conv2d(ch, ch, 3, stride=stride, padding=dilation, dilation=dilation, groups=ch,
                              bias=False)

    def forward(self, x):
        return self.conv(x)


class SeqConvBNAct(nn.Module):
    """Conv -> BatchNorm -> PReLU held in a Sequential `cbr` (authors' cnn_utils.CBR, used by the decoder)."""

    def __init__(self, cin: int, cout: int, k: int, groups: int = 1):
        super().__init__()
        self.cbr = nn.Sequential(
            nn.Conv2d(cin, cout, k, stride=1, padding=(k - 1) // 2, groups=groups, bias=False),
            nn.BatchNorm2d(cout),
            nn.PReLU(cout),
        )

    def forward(self, x):
        return self.cbr(x)


class SeqBNAct(nn.Module):
    """BatchNorm -> PReLU held in a Sequential `br` (authors' cnn_utils.BR, used by the decoder)."""

    def __init__(self, ch: int):
        super().__init__()
        self.br = nn.Sequential(nn.BatchNorm2d(ch), nn.PReLU(ch))

    def forward(self, x):
        return self.br(x)


class ChannelShuffle(nn.Module):
    """ShuffleNet channel shuffle: [g, c/g] channel layout transposed to [c/g, g] (authors' cnn_utils.Shuffle)."""

    def __init__(self, groups: int):
        super().__init__()
        self.groups = groups

    def forward(self, x):
        n, c, h, w = x.shape
        x = x.reshape(n, self.groups, c // self.groups, h, w).transpose(1, 2)
        return x.reshape(n, c, h, w)


# --------------------------------------------------------------------------------------------------------------
# Encoder (EESPNet, paper section 3 / authors' nn_layers/eesp.py and model/classification/espnetv2.py)
# --------------------------------------------------------------------------------------------------------------
class EESP(nn.Module):
    """Extremely Efficient Spatial Pyramid block: reduce -> split -> transform -> merge (paper Fig. 1c/d).

    A grouped 1x1 conv (k groups) reduces `cin` to n = cout/k channels; k depth-wise 3x3 convs with growing
    dilation run on that in parallel; their outputs are summed cumulatively (hierarchical feature fusion, which
    removes gridding artefacts), concatenated, BN+PReLU'd, and expanded by a grouped 1x1 conv + BN. Kernel sizes
    3, 5, 7, ... (dilations 1, 2, 3, ...) beyond the level's receptive-field limit fall back to 3 and the list
    is sorted ascending. Stride 1: residual add with the input, then PReLU (`module_act`). Stride 2 (inside a
    DownSampler): returns the expanded map unactivated; the DownSampler fuses and activates it (`module_act`
    exists in the checkpoint but is unused there)."""

    def __init__(self, cin: int, cout: int, stride: int, k: int, r_lim: int):
        super().__init__()
        n = cout // k
        assert n * k == cout, "EESP output width must split evenly over the branches"
        self.stride = stride
        self.residual = stride == 1 and cin == cout
        self.proj_1x1 = ConvBNAct(cin, n, 1, groups=k)
        ksizes = sorted(3 + 2 * i if 3 + 2 * i <= r_lim else 3 for i in range(k))
        self.spp_dw = nn.ModuleList(DilatedDWConv(n, stride, (ks - 1) // 2) for ks in ksizes)
        self.conv_1x1_exp = ConvBN(cout, cout, 1, groups=k)
        self.br_after_cat = BNAct(cout)
        self.module_act = nn.PReLU(cout)

    def forward(self, x):
        reduced = self.proj_1x1(x)
        fused = []
        for branch in self.spp_dw:
            y = branch(reduced)
            if fused:
                y = y + fused[-1]  # hierarchical feature fusion
            fused.append(y)
        out = self.conv_1x1_exp(self.br_after_cat(torch.cat(fused, 1)))
        if self.stride == 2:
            return out
        if self.residual:
            out = out + x
        return self.module_act(out)


class DownSampler(nn.Module):
    """Strided EESP unit (paper Fig. 3): halves the resolution and widens `cin` to `cout`.

    Concatenates a 3x3/2 average pool of the input (cin channels) with a stride-2 EESP (cout - cin channels),
    adds the input-reinforcement path (the normalised RGB image average-pooled down to the same resolution,
    then 3x3 conv-BN-PReLU and 1x1 conv-BN to cout channels), and applies PReLU. The authors pool the image
    in a loop until its height matches; every halving is ceil(h/2) on both paths, so that is a fixed number of
    poolings per level, and the caller passes the image already pooled to this block's output size."""

    def __init__(self, cin: int, cout: int, k: int, r_lim: int):
        super().__init__()
        self.eesp = EESP(cin, cout - cin, stride=2, k=k, r_lim=r_lim)
        self.avg = nn.AvgPool2d(kernel_size=3, stride=2, padding=1)
        self.inp_reinf = nn.Sequential(
            ConvBNAct(REINF_CHANNELS, REINF_CHANNELS, 3),
            ConvBN(REINF_CHANNELS, cout, 1),
        )
        self.act = nn.PReLU(cout)

    def forward(self, x, image_at_out_res):
        out = torch.cat([self.avg(x), self.eesp(x)], 1)
        out = out + self.inp_reinf(image_at_out_res)
        return self.act(out)


def halve_image(img):
    """The image pooling of the input-reinforcement path: 3x3 average pool, stride 2, padding 1 (pad counted)."""
    return F.avg_pool2d(img, kernel_size=3, stride=2, padding=1)


class EESPNetEncoder(nn.Module):
    """EESPNet (s = 2.0) trunk up to level 4 (1/16 resolution); the ImageNet model's level5 and classifier are
    deleted by the authors' segmentation model and absent from the checkpoint.

    level1: 3x3/2 conv-BN-PReLU (1/2); level2_0: DownSampler (1/4); level3_0 + 3 EESP (1/8);
    level4_0 + 7 EESP (1/16). Input reinforcement is on. Returns the four level outputs for the decoder."""

    def __init__(self):
        super().__init__()
        c1, c2, c3, c4 = ENC_CHANNELS
        self.level1 = ConvBNAct(REINF_CHANNELS, c1, 3, stride=2)
        self.level2_0 = DownSampler(c1, c2, k=BRANCHES, r_lim=RECEPTIVE_LIMITS[0])
        self.level3_0 = DownSampler(c2, c3, k=BRANCHES, r_lim=RECEPTIVE_LIMITS[1])
        self.level3 = nn.ModuleList(
            EESP(c3, c3, stride=1, k=BRANCHES, r_lim=RECEPTIVE_LIMITS[2]) for _ in range(ENC_REPEATS[0]))
        self.level4_0 = DownSampler(c3, c4, k=BRANCHES, r_lim=RECEPTIVE_LIMITS[2])
        self.level4 = nn.ModuleList(
            EESP(c4, c4, stride=1, k=BRANCHES, r_lim=RECEPTIVE_LIMITS[3]) for _ in range(ENC_REPEATS[1]))

    def forward(self, x):
        img2 = halve_image(x)        # 1/2
        img4 = halve_image(img2)     # 1/4
        img8 = halve_image(img4)     # 1/8
        img16 = halve_image(img8)    # 1/16
        l1 = self.level1(x)
        l2 = self.level2_0(l1, img4)
        l3 = self.level3_0(l2, img8)
        for block in self.level3:
            l3 = block(l3)
        l4 = self.level4_0(l3, img16)
        for block in self.level4:
            l4 = block(l4)
        return l1, l2, l3, l4


# --------------------------------------------------------------------------------------------------------------
# Shape-generic adaptive average pooling
# --------------------------------------------------------------------------------------------------------------
def _window_bounds(n_in, n_out):
    """Adaptive-pooling windows along one axis, as PyTorch defines them: output i averages input
    [floor(i * n_in / n_out), ceil((i + 1) * n_in / n_out)). Integer tensor arithmetic on (symbolic) sizes."""
    i = torch.arange(n_out, dtype=torch.int64)
    start = (i * n_in) // n_out
    end = ((i + 1) * n_in + n_out - 1) // n_out
    return start, end


def _pool_axis_taps(x, dim: int, n_out, taps: int):
    """Adaptive average pooling along `dim` as a sum of `taps` gathers: tap k reads input start_i + k (clamped
    into range) and counts only where k < window length; the sum is divided by the length. Exact whenever
    every window is at most `taps` long."""
    n_in = x.shape[dim]
    start, end = _window_bounds(n_in, n_out)
    length = end - start
    view = [1, 1, 1, 1]
    view[dim] = -1
    last = torch.zeros_like(start) + (n_in - 1)
    acc = x.index_select(dim, start)
    for k in range(1, taps):
        tap = x.index_select(dim, torch.minimum(start + k, last))
        acc = acc + tap * (length > k).to(x.dtype).reshape(view)
    return acc / length.to(x.dtype).reshape(view)


def _pool_matrix(n_in, n_out, dtype):
    """[n_out, n_in] averaging matrix of the adaptive-pooling windows (row i: 1/len on its window)."""
    start, end = _window_bounds(n_in, n_out)
    j = torch.arange(n_in, dtype=torch.int64).unsqueeze(0)
    inside = (j >= start.unsqueeze(1)) & (j < end.unsqueeze(1))
    return inside.to(dtype) / (end - start).to(dtype).unsqueeze(1)


def adaptive_avg_pool(x, out_h, out_w, max_ratio: int):
    """F.adaptive_avg_pool2d(x, (out_h, out_w)) written with ops that stay shape-generic in ONNX.

    `max_ratio` is a static bound on in_size / out_size. A window spans fewer than ratio + 2 inputs, so with
    ratio <= 2 three gather taps per axis cover every window (separable: rows, then columns); wider ratios use
    averaging matrices (out = P_h @ x @ P_w^T). torch.export keeps out_h, out_w and the input sizes symbolic,
    so the window bounds are computed in the graph at run time."""
    if max_ratio <= 2:
        y = _pool_axis_taps(x, 2, out_h, max_ratio + 1)
        return _pool_axis_taps(y, 3, out_w, max_ratio + 1)
    p_h = _pool_matrix(x.shape[2], out_h, x.dtype)
    p_w = _pool_matrix(x.shape[3], out_w, x.dtype)
    return torch.matmul(torch.matmul(p_h, x), p_w.transpose(0, 1))


def _check_pooling() -> None:
    """The pooling helpers against F.adaptive_avg_pool2d on the size pairs the decoder meets."""
    g = torch.Generator().manual_seed(0)
    for n in list(range(3, 70)) + [120, 128, 240, 256, 320, 512]:
        x = torch.rand(1, 2, n, n + 7, generator=g)
        for num, den in PYR_SCALES:
            if num > den and den > 1:  # up-branch: pool ceil(s n) back to n
                up_h, up_w = ceil_scaled(n, num, den), ceil_scaled(n + 7, num, den)
                xx = torch.rand(1, 2, up_h, up_w, generator=g)
                got = adaptive_avg_pool(xx, n, n + 7, max_ratio=-(-num // den))
                want = F.adaptive_avg_pool2d(xx, (n, n + 7))
            elif num < den:
                oh = max(ceil_scaled(n, num, den), PYR_MIN_SIZE)
                ow = max(ceil_scaled(n + 7, num, den), PYR_MIN_SIZE)
                got = adaptive_avg_pool(x, oh, ow, max_ratio=den // num)
                want = F.adaptive_avg_pool2d(x, (oh, ow))
            else:
                continue
            assert got.shape == want.shape and torch.allclose(got, want, atol=1e-6), (n, num, den)


# --------------------------------------------------------------------------------------------------------------
# Decoder (authors' nn_layers/efficient_pyramid_pool.py, nn_layers/efficient_pt.py)
# --------------------------------------------------------------------------------------------------------------
class EfficientPyrPool(nn.Module):
    """Efficient pyramid pooling (EdgeNets EfficientPyrPool): 1x1 projection to 10 channels, then five
    depth-wise 3x3 convs applied at scales 2.0, 1.5, 1.0, 0.5 and 0.1 of the projected map, each brought back to
    the map's size; BN+PReLU on the 50-channel concatenation, channel shuffle (5 groups), grouped 3x3 conv-BN-
    PReLU to 10 channels, 1x1 conv to `cout`, and BN+PReLU unless this is the last (classifier) block, where the
    1x1 conv has a bias instead.

    Branch at scale s on an h x w map: target size (max(ceil(s h), 5), max(ceil(s w), 5)).
      s > 1: bilinear resize up (align_corners=True) -> conv -> adaptive average pool back to h x w;
      s < 1: adaptive average pool down -> conv -> bilinear resize back (align_corners=True);
      s = 1: conv only.
    The adaptive pools have input-size-dependent windows [floor(i*in/out), ceil((i+1)*in/out)); the sizes are
    integer SymInt arithmetic and the pooling is `adaptive_avg_pool`, so the ONNX graph computes the windows at
    run time (2.0: exact 2x2 average pool; 1.5 and 0.5: three gather taps per axis; 0.1: averaging matrices).
    For the up-scales the >= 5 clamp only changes anything when h or w < 3 (input side < 48), which this
    exporter does not support; it is applied to the down-scales."""

    def __init__(self, cin: int, proj: int, cout: int, last_layer_br: bool = True):
        super().__init__()
        self.stages = nn.ModuleList(
            nn.Conv2d(proj, proj, 3, stride=1, padding=1, groups=proj, bias=False) for _ in PYR_SCALES)
        self.projection_layer = SeqConvBNAct(cin, proj, 1)
        n = len(PYR_SCALES)
        self.merge_layer = nn.Sequential(
            SeqBNAct(proj * n),
            ChannelShuffle(n),
            SeqConvBNAct(proj * n, proj, 3, groups=proj),
            nn.Conv2d(proj, cout, 1, stride=1, bias=not last_layer_br),
        )
        self.last_layer_br = last_layer_br
        if last_layer_br:
            self.br = SeqBNAct(cout)

    def forward(self, x):
        x = self.projection_layer(x)
        h, w = x.shape[2], x.shape[3]
        if isinstance(h, int) and isinstance(w, int):
            assert h >= 3 and w >= 3, "input side below 48 pixels is not supported"
        branches = []
        for (num, den), stage in zip(PYR_SCALES, self.stages):
            if num == den:
                branches.append(stage(x))
                continue
            hs, ws = ceil_scaled(h, num, den), ceil_scaled(w, num, den)
            if num > den:
                y = stage(F.interpolate(x, size=(hs, ws), mode="bilinear", align_corners=True))
                if den == 1:  # integer up-scale: the windows are exactly num x num
                    y = F.avg_pool2d(y, kernel_size=num, stride=num)
                else:         # 1.5: ceil(1.5 h) / h <= 2
                    y = adaptive_avg_pool(y, h, w, max_ratio=-(-num // den))
            else:
                hs, ws = torch.sym_max(hs, PYR_MIN_SIZE), torch.sym_max(ws, PYR_MIN_SIZE)
                # h / max(ceil(h num / den), 5) <= den / num
                y = stage(adaptive_avg_pool(x, hs, ws, max_ratio=den // num))
                y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=True)
            branches.append(y)
        out = self.merge_layer(torch.cat(branches, 1))
        return self.br(out) if self.last_layer_br else out


class EfficientPWConv(nn.Module):
    """Encoder-to-decoder projection (EdgeNets EfficientPWConv): a grouped 3x3 conv-BN-PReLU (groups =
    gcd(cin, cout)) gated channel-wise by sigmoid(1x1 conv(global average pool of the input)), a squeeze-
    excitation-like weighting."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.wt_layer = nn.Sequential(
            nn.AdaptiveAvgPool2d(1),
            nn.Conv2d(cin, cout, 1, stride=1, padding=0, bias=False),
            nn.Sigmoid(),
        )
        self.expansion_layer = SeqConvBNAct(cin, cout, 3, groups=math.gcd(cin, cout))

    def forward(self, x):
        return self.expansion_layer(x) * self.wt_layer(x)


class ESPNetv2Segmentation(nn.Module):
    """ESPNetv2 segmentation network (authors' model/segmentation/espnetv2.py, dataset 'city').

    Encoder outputs at 1/2, 1/4, 1/8, 1/16. Decoder: pyramid block on level 4 (-> 64 ch); then three times
    upsample x2 (bilinear, align_corners=True), add the EfficientPWConv projection of the next-finer encoder
    level (level 3 -> 64, level 2 -> 48, level 1 -> 32 ch), BN+PReLU, pyramid block (-> 48, 32, 20 ch).
    Returns class logits at 1/2 resolution (the authors' forward then resizes to the input size; the export
    wrapper does that)."""

    def __init__(self):
        super().__init__()
        c1, c2, c3, c4 = ENC_CHANNELS
        d1, d2, d3, d4 = DEC_CHANNELS
        self.base_net = EESPNetEncoder()
        self.bu_dec_l1 = EfficientPyrPool(c4, PYR_PROJ, d1)
        self.bu_dec_l2 = EfficientPyrPool(d1, PYR_PROJ, d2)
        self.bu_dec_l3 = EfficientPyrPool(d2, PYR_PROJ, d3)
        self.bu_dec_l4 = EfficientPyrPool(d3, PYR_PROJ, d4, last_layer_br=False)
        self.merge_enc_dec_l2 = EfficientPWConv(c3, d1)
        self.merge_enc_dec_l3 = EfficientPWConv(c2, d2)
        self.merge_enc_dec_l4 = EfficientPWConv(c1, d3)
        self.bu_br_l2 = nn.Sequential(nn.BatchNorm2d(d1), nn.PReLU(d1))
        self.bu_br_l3 = nn.Sequential(nn.BatchNorm2d(d2), nn.PReLU(d2))
        self.bu_br_l4 = nn.Sequential(nn.BatchNorm2d(d3), nn.PReLU(d3))

    @staticmethod
    def up2(x):
        return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)

    def forward(self, x):
        l1, l2, l3, l4 = self.base_net(x)
        y = self.bu_dec_l1(l4)
        y = self.bu_dec_l2(self.bu_br_l2(self.merge_enc_dec_l2(l3) + self.up2(y)))
        y = self.bu_dec_l3(self.bu_br_l3(self.merge_enc_dec_l3(l2) + self.up2(y)))
        y = self.bu_dec_l4(self.bu_br_l4(self.merge_enc_dec_l4(l1) + self.up2(y)))
        return y


class Segmenter(nn.Module):
    """What the ONNX graph computes: RGB 0..255 -> /255 -> ImageNet mean/std -> ESPNetv2 -> bilinear
    (align_corners=True) resize of the 1/2-resolution logits to the input size."""

    def __init__(self, net: ESPNetv2Segmentation):
        super().__init__()
        self.net = net
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, rgb):
        x = (rgb / 255.0 - self.mean) / self.std
        logits = self.net(x)
        return F.interpolate(logits, size=(rgb.shape[2], rgb.shape[3]), mode="bilinear", align_corners=True)


# --------------------------------------------------------------------------------------------------------------
# Loading, export, checks
# --------------------------------------------------------------------------------------------------------------
def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load_model(checkpoint: Path) -> Segmenter:
    digest = sha256_of(checkpoint)
    if digest != CHECKPOINT_SHA256:
        print(f"warning: checkpoint sha256 {digest} is not the known {CHECKPOINT_SHA256}", file=sys.stderr)
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "state_dict" in state and not any(k.startswith("base_net.") for k in state):
        state = state["state_dict"]
    torch.manual_seed(0)  # parameters are all overwritten below; this only fixes the throw-away init
    net = ESPNetv2Segmentation()
    expected = net.state_dict()
    net.load_state_dict(state, strict=True)  # raises on any missing or unexpected key or shape mismatch
    print(f"loaded {len(state)} tensors strictly ({len(expected)} in the model), checkpoint sha256 {digest}")
    if len(state) != CHECKPOINT_TENSORS:
        print(f"warning: expected {CHECKPOINT_TENSORS} tensors", file=sys.stderr)
    return Segmenter(net).eval()


def export_onnx(model: Segmenter, out: Path) -> None:
    import onnx

    # H = 16 h16, W = 16 w16: the decoder adds maps of H/8 and 2 (H/16), so only multiples of 16 are valid.
    h16 = torch.export.Dim("h16", min=3, max=512)
    w16 = torch.export.Dim("w16", min=3, max=512)
    H, W = 16 * h16, 16 * w16
    example = torch.zeros(1, 3, 512, 1024)
    with torch.no_grad():
        # strict=True (the TorchDynamo front end) reads each block's sizes from the tensor the code reads them
        # from (the pyramid block's projection conv output) instead of re-deriving them from the input shape.
        # That is the structure of the reference graph: the BatchNorm behind that conv stays unfused (its
        # output also feeds Shape), and the logits match the reference bit for bit. The non-strict front end
        # gives an equally valid graph whose logits differ by ~1e-5 (float rounding of the extra BN fold).
        exported = torch.export.export(model, (example,), dynamic_shapes={"rgb": {2: H, 3: W}}, strict=True)
        program = torch.onnx.export(
            exported,
            dynamo=True,
            input_names=["rgb"],
            output_names=["logits"],
            opset_version=OPSET,
            external_data=False,
            optimize=True,
            verbose=False,
        )
    proto = program.model_proto
    proto.doc_string = DOC_STRING
    rename_symbolic_dims(proto)
    # Node metadata (stack traces, scopes) would tie the bytes to this file's path; keep the graph clean.
    for node in proto.graph.node:
        del node.metadata_props[:]
    onnx.checker.check_model(proto, full_check=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(proto.SerializeToString(deterministic=True))


def rename_symbolic_dims(proto) -> None:
    """Name the dynamic input/output dims H and W (torch.export calls them 16*sNN) and the symbols inside the
    intermediate shapes h16 and w16."""
    import re

    dims = proto.graph.input[0].type.tensor_type.shape.dim
    symbols = {}
    for dim, full, short in ((dims[2], "H", "h16"), (dims[3], "W", "w16")):
        match = re.fullmatch(r"16\*(\w+)", dim.dim_param)
        if not match:
            raise RuntimeError(f"unexpected dynamic dim {dim.dim_param!r}")
        symbols[match.group(1)] = short
    pattern = re.compile(r"\b(" + "|".join(map(re.escape, symbols)) + r")\b")

    def rename(value):
        for dim in value.type.tensor_type.shape.dim:
            if dim.dim_param:
                param = pattern.sub(lambda m: symbols[m.group(1)], dim.dim_param)
                dim.dim_param = {"16*h16": "H", "16*w16": "W"}.get(param, param)

    for value in list(proto.graph.input) + list(proto.graph.output) + list(proto.graph.value_info):
        rename(value)
    # torch.export records the size ranges as a printed dict whose order follows Python's string hashing
    # (PYTHONHASHSEED), which would make the bytes vary between runs; write it renamed and sorted.
    for prop in proto.graph.metadata_props:
        if prop.key.endswith(".range_constraints"):
            ranges = re.findall(r"([^{},:]+): (VR\[[^\]]*\])", prop.value)
            named = {pattern.sub(lambda m: symbols[m.group(1)], k.strip()): v for k, v in ranges}
            named = {{"16*h16": "H", "16*w16": "W"}.get(k, k): v for k, v in named.items()}
            prop.value = "{" + ", ".join(f"{k}: {named[k]}" for k in sorted(named)) + "}"


def make_session(path: Path, threads: int):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


def synthetic_frame(w: int, h: int) -> np.ndarray:
    """A deterministic smooth RGB test pattern, 0..255, [1,3,h,w] float32."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r = 127.5 + 127.5 * np.sin(xx / 37.0 + yy / 53.0)
    g = 127.5 + 127.5 * np.cos(xx / 23.0 - yy / 41.0)
    b = np.clip(255.0 * yy / max(h - 1, 1), 0, 255)
    return np.stack([r, g, b])[None].astype(np.float32)


def load_frame(path: Path, w: int, h: int) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB").resize((w, h), Image.BILINEAR)
        arr = np.asarray(im, dtype=np.float32)
    return np.ascontiguousarray(arr.transpose(2, 0, 1)[None])


def verify_sizes(model: Segmenter, onnx_path: Path, threads: int, frame: Path | None) -> bool:
    """Run the exported graph at several sizes (W x H) against the PyTorch model: one graph must serve all."""
    sizes = [(1024, 512), (640, 480), (720, 400), (512, 256), (368, 208), (256, 128), (48, 48)]
    sess = make_session(onnx_path, threads)
    ok = True
    print("exported graph vs PyTorch model (%s):" % ("frame " + frame.name if frame else "synthetic pattern"))
    for w, h in sizes:
        x = load_frame(frame, w, h) if frame else synthetic_frame(w, h)
        with torch.no_grad():
            ref = model(torch.from_numpy(x)).numpy()
        got = sess.run(["logits"], {"rgb": x})[0]
        assert got.shape == (1, NUM_CLASSES, h, w), got.shape
        diff = float(np.abs(got - ref).max())
        agree = float((got.argmax(1) == ref.argmax(1)).mean())
        good = diff <= 1e-3
        ok &= good
        print(f"  {w:4d}x{h:<4d} max|diff| {diff:.2e}  argmax agreement {100 * agree:.4f} %"
              f"{'' if good else '  <-- FAIL'}")
    return ok


def list_frames(folder: Path) -> list[Path]:
    exts = {".png", ".jpg", ".jpeg", ".bmp"}
    frames = sorted(p for p in folder.iterdir() if p.suffix.lower() in exts)
    if not frames and (folder / "images").is_dir():
        frames = sorted(p for p in (folder / "images").iterdir() if p.suffix.lower() in exts)
    return frames


def check_against_reference(ours: Path, reference: Path, frames: list[Path], threads: int) -> bool:
    sess_ours, sess_ref = make_session(ours, threads), make_session(reference, threads)
    sizes = [(1024, 512), (640, 480), (512, 256)]
    ok = True
    print(f"exported graph vs reference {reference.name} on {len(frames)} frames:")
    for w, h in sizes:
        t0 = time.perf_counter()
        max_diff, differing, total = 0.0, 0, 0
        for f in frames:
            x = load_frame(f, w, h)
            a = sess_ours.run(["logits"], {"rgb": x})[0]
            b = sess_ref.run(["logits"], {"rgb": x})[0]
            if a.shape != b.shape:
                print(f"  {w}x{h} {f.name}: shape {a.shape} vs {b.shape}")
                ok = False
                break
            max_diff = max(max_diff, float(np.abs(a - b).max()))
            differing += int((a.argmax(1) != b.argmax(1)).sum())
            total += h * w
        good = max_diff <= 1e-3 and differing == 0
        ok &= good
        print(f"  {w:4d}x{h:<4d} max|logit diff| {max_diff:.3e}  argmax agreement "
              f"{100.0 * (total - differing) / max(total, 1):.6f} % ({differing} of {total} pixels differ)"
              f"  [{time.perf_counter() - t0:.0f} s]{'' if good else '  <-- FAIL'}")
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path, help="espnetv2_s_2.0_city_1024x512.pth")
    ap.add_argument("out", type=Path, help="ONNX file to write")
    ap.add_argument("--check", type=Path, metavar="REFERENCE.onnx", help="compare with this ONNX graph")
    ap.add_argument("--frames", type=Path, metavar="DIR", help="image folder for --check (or DIR/images)")
    ap.add_argument("--max-frames", type=int, default=0, help="use only the first N frames (0 = all)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime / torch CPU threads")
    args = ap.parse_args(argv)
    if args.check and not args.frames:
        ap.error("--check needs --frames DIR")

    torch.set_num_threads(args.threads)
    _check_ceil_formula()
    _check_pooling()
    model = load_model(args.checkpoint)

    t0 = time.perf_counter()
    export_onnx(model, args.out)
    print(f"exported {args.out} in {time.perf_counter() - t0:.1f} s")
    size = args.out.stat().st_size
    print(f"sha256 {sha256_of(args.out)}  {size} bytes  {args.out}")

    frames = list_frames(args.frames) if args.frames else []
    if args.frames and not frames:
        print(f"no image files in {args.frames}", file=sys.stderr)
        return 2
    if args.max_frames > 0:
        frames = frames[: args.max_frames]

    ok = verify_sizes(model, args.out, args.threads, frames[0] if frames else None)
    if args.check:
        ok &= check_against_reference(args.out, args.check, frames, args.threads)
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
