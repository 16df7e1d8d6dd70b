//! The few neural-network operations XFeat and EfficientNet-Lite need, on CHW float tensors
//! (batch 1): convolution by im2col and a matrix product (matrixmultiply's sgemm, parallel over
//! column bands with rayon), depthwise convolution, TensorFlow's SAME padding, ReLU6,
//! inference-mode batch norm without affine terms fused with ReLU, average pooling, instance
//! norm, bilinear resizing (PyTorch's align_corners = False) and 8x8 space-to-depth.
//! Shapes come from a weights file, so every operation checks them and returns an error rather
//! than panicking (an [`Error::Check`]: what runs the network names it).

use crate::error::{Error, Result};
use rayon::prelude::*;

/// A CHW tensor.
#[derive(Debug, Clone, PartialEq)]
pub struct Chw {
    /// Channels.
    pub c: usize,
    /// Height.
    pub h: usize,
    /// Width.
    pub w: usize,
    /// The values, channel by channel, each plane row-major (c x h x w).
    pub data: Vec<f32>,
}

impl Chw {
    /// A tensor of `c` x `h` x `w` zeros.
    pub fn zeros(c: usize, h: usize, w: usize) -> Chw {
        Chw { c, h, w, data: vec![0.0; c * h * w] }
    }
    /// Channel `c`'s plane (h x w values, row-major).
    pub fn plane(&self, c: usize) -> &[f32] {
        &self.data[c * self.h * self.w..(c + 1) * self.h * self.w]
    }
    /// Element-wise sum of two tensors of one shape.
    pub fn plus(mut self, o: &Chw) -> Result<Chw> {
        if (self.c, self.h, self.w) != (o.c, o.h, o.w) || self.data.len() != o.data.len() {
            return Err(Error::check(format!("cannot add a {}x{}x{} tensor to a {}x{}x{} one", o.c, o.h, o.w, self.c, self.h, self.w)));
        }
        self.data.iter_mut().zip(&o.data).for_each(|(a, b)| *a += b);
        Ok(self)
    }
    /// Whether `data` holds exactly c x h x w values.
    pub fn is_consistent(&self) -> bool {
        self.c.checked_mul(self.h).and_then(|v| v.checked_mul(self.w)) == Some(self.data.len())
    }
}

/// Columns per im2col band: bounds the scratch of one band (k*k*Cin x BAND floats).
const BAND: usize = 1024;

/// im2col of output columns [b0, b1) into `cols` (cin*k*k rows of b1 - b0), copying row
/// segments rather than single elements.
#[allow(clippy::too_many_arguments)]
fn im2col_band(x: &Chw, k: usize, stride: usize, pad: usize, wo: usize, b0: usize, b1: usize, cols: &mut [f32]) {
    let (h, w) = (x.h as isize, x.w as isize);
    let nb = b1 - b0;
    for ci in 0..x.c {
        let src = x.plane(ci);
        for ky in 0..k {
            for kx in 0..k {
                let row = &mut cols[((ci * k + ky) * k + kx) * nb..][..nb];
                let mut p = b0;
                while p < b1 {
                    let (oy, ox0) = (p / wo, p % wo);
                    let ox1 = wo.min(ox0 + (b1 - p));
                    let dst = &mut row[p - b0..p - b0 + (ox1 - ox0)];
                    let iy = (oy * stride + ky) as isize - pad as isize;
                    if iy < 0 || iy >= h {
                        dst.fill(0.0);
                    } else {
                        let line = &src[iy as usize * x.w..(iy as usize + 1) * x.w];
                        if stride == 1 {
                            // ix = ox + kx - pad: one contiguous run, zeros where it leaves the row
                            let first = ox0 as isize + kx as isize - pad as isize;
                            let lo = (-first).clamp(0, dst.len() as isize) as usize;
                            let hi = (w - first).clamp(lo as isize, dst.len() as isize) as usize;
                            dst[..lo].fill(0.0);
                            dst[hi..].fill(0.0);
                            if hi > lo {
                                let s0 = (first + lo as isize) as usize;
                                dst[lo..hi].copy_from_slice(&line[s0..s0 + (hi - lo)]);
                            }
                        } else {
                            for (j, slot) in dst.iter_mut().enumerate() {
                                let ix = ((ox0 + j) * stride + kx) as isize - pad as isize;
                                *slot = if ix >= 0 && ix < w { line[ix as usize] } else { 0.0 };
                            }
                        }
                    }
                    p += ox1 - ox0;
                }
            }
        }
    }
}

/// 2-D convolution of `x` with `weight` [cout, cin, k, k], square stride and zero padding, plus
/// an optional bias. A 1x1 convolution with stride 1 multiplies the input directly. Fails when
/// the sizes do not fit together.
pub fn conv2d(x: &Chw, weight: &[f32], bias: Option<&[f32]>, cout: usize, k: usize, stride: usize, pad: usize) -> Result<Chw> {
    let (cin, h, w) = (x.c, x.h, x.w);
    let want = cout.checked_mul(cin).and_then(|v| v.checked_mul(k)).and_then(|v| v.checked_mul(k));
    if want != Some(weight.len()) || k == 0 || stride == 0 || !x.is_consistent() {
        return Err(Error::check(format!(
            "convolution weights of {} values do not fit {cout} outputs, {cin} inputs and a {k}x{k} kernel (stride {stride})",
            weight.len()
        )));
    }
    if bias.is_some_and(|b| b.len() != cout) {
        return Err(Error::check(format!("convolution bias of {} values for {cout} outputs", bias.map_or(0, <[f32]>::len))));
    }
    if h + 2 * pad < k || w + 2 * pad < k {
        return Err(Error::check(format!("{k}x{k} kernel on a {h}x{w} input")));
    }
    let ho = (h + 2 * pad - k) / stride + 1;
    let wo = (w + 2 * pad - k) / stride + 1;
    let n = ho * wo;
    let kk = cin * k * k;
    let direct = k == 1 && stride == 1 && pad == 0;
    let mut out = Chw::zeros(cout, ho, wo);
    // each band computes output columns [b0, b1) of every output channel
    let bands: Vec<(usize, Vec<f32>)> = (0..n.div_ceil(BAND))
        .into_par_iter()
        .map(|band| {
            let (b0, b1) = (band * BAND, ((band + 1) * BAND).min(n));
            let nb = b1 - b0;
            let mut res = vec![0.0f32; cout * nb];
            let cols;
            // B = cols [kk x nb] (row stride nb), or the input itself (row stride n, offset b0)
            let (b_ptr, rsb) = if direct {
                (x.data[b0..].as_ptr(), n as isize)
            } else {
                let mut c = vec![0.0f32; kk * nb];
                im2col_band(x, k, stride, pad, wo, b0, b1, &mut c);
                cols = c;
                (cols.as_ptr(), nb as isize)
            };
            // SAFETY: a is cout x kk, b is kk x nb with the row stride given, c is cout x nb; all
            // three live for the call and c does not alias them.
            unsafe {
                matrixmultiply::sgemm(cout, kk, nb, 1.0, weight.as_ptr(), kk as isize, 1, b_ptr, rsb, 1, 0.0, res.as_mut_ptr(), nb as isize, 1);
            }
            (b0, res)
        })
        .collect();
    for (b0, res) in bands {
        let nb = res.len() / cout;
        for co in 0..cout {
            out.data[co * n + b0..co * n + b0 + nb].copy_from_slice(&res[co * nb..(co + 1) * nb]);
        }
    }
    if let Some(b) = bias {
        for co in 0..cout {
            out.data[co * n..(co + 1) * n].iter_mut().for_each(|v| *v += b[co]);
        }
    }
    Ok(out)
}

/// TensorFlow's SAME padding of a side of `n` values for a `k` kernel at `stride`: (before,
/// after), the odd value after, so that the output has ceil(n / stride) values (what ONNX calls
/// `SAME_UPPER`). For stride 1 and an odd kernel it is (k - 1) / 2 on each side.
pub fn same_padding(n: usize, k: usize, stride: usize) -> (usize, usize) {
    let out = n.div_ceil(stride.max(1));
    let total = ((out.max(1) - 1) * stride + k).saturating_sub(n);
    (total / 2, total - total / 2)
}

/// `x` with zero rows added above (`top`) and below (`bottom`), zero columns left and right.
pub fn pad(x: &Chw, top: usize, bottom: usize, left: usize, right: usize) -> Chw {
    let (h, w) = (x.h + top + bottom, x.w + left + right);
    let mut out = Chw::zeros(x.c, h, w);
    if x.h * x.w == 0 {
        return out;
    }
    out.data.par_chunks_mut(h * w).zip(x.data.par_chunks(x.h * x.w)).for_each(|(dst, src)| {
        for (y, row) in src.chunks(x.w).enumerate() {
            dst[(y + top) * w + left..][..x.w].copy_from_slice(row);
        }
    });
    out
}

/// Depthwise 2-D convolution without padding: channel c of `x` with kernel `weight[c]` (k x k,
/// weights [C, 1, k, k]) at `stride`, plus `bias[c]`; each output value is accumulated over the
/// kernel's rows and columns in order. Fails when the sizes do not fit together.
pub fn depthwise_conv2d(x: &Chw, weight: &[f32], bias: &[f32], k: usize, stride: usize) -> Result<Chw> {
    if k == 0 || stride == 0 || x.c.checked_mul(k * k) != Some(weight.len()) || bias.len() != x.c || !x.is_consistent() {
        return Err(Error::check(format!(
            "depthwise weights of {} values and {} biases do not fit {} channels and a {k}x{k} kernel (stride {stride})",
            weight.len(),
            bias.len(),
            x.c
        )));
    }
    if x.h < k || x.w < k {
        return Err(Error::check(format!("{k}x{k} kernel on a {}x{} input", x.h, x.w)));
    }
    let (ho, wo) = ((x.h - k) / stride + 1, (x.w - k) / stride + 1);
    let mut out = Chw::zeros(x.c, ho, wo);
    out.data.par_chunks_mut(ho * wo).enumerate().for_each(|(c, dst)| {
        let (src, wt) = (x.plane(c), &weight[c * k * k..(c + 1) * k * k]);
        dst.fill(bias[c]);
        for ky in 0..k {
            for kx in 0..k {
                let wv = wt[ky * k + kx];
                for oy in 0..ho {
                    let line = &src[(oy * stride + ky) * x.w + kx..];
                    let row = &mut dst[oy * wo..(oy + 1) * wo];
                    if stride == 1 {
                        row.iter_mut().zip(line).for_each(|(o, &v)| *o += wv * v);
                    } else {
                        row.iter_mut().zip(line.iter().step_by(stride)).for_each(|(o, &v)| *o += wv * v);
                    }
                }
            }
        }
    });
    Ok(out)
}

/// ReLU6, min(max(v, 0), 6), in place.
pub fn relu6(x: &mut Chw) {
    x.data.par_iter_mut().for_each(|v| *v = v.clamp(0.0, 6.0));
}

/// Inference-mode BatchNorm2d(affine = False), eps 1e-5, followed by ReLU, in place.
pub fn batchnorm_relu(x: &mut Chw, mean: &[f32], var: &[f32]) -> Result<()> {
    if mean.len() != x.c || var.len() != x.c || !x.is_consistent() {
        return Err(Error::check(format!("batch norm of {} channels with {} means and {} variances", x.c, mean.len(), var.len())));
    }
    let hw = x.h * x.w;
    if hw == 0 {
        return Ok(());
    }
    x.data.par_chunks_mut(hw).enumerate().for_each(|(c, plane)| {
        let inv = 1.0 / (var[c] + 1e-5).sqrt();
        let m = mean[c];
        plane.iter_mut().for_each(|v| *v = ((*v - m) * inv).max(0.0));
    });
    Ok(())
}

/// AvgPool2d(k, stride k) on sizes divisible by k.
pub fn avg_pool(x: &Chw, k: usize) -> Result<Chw> {
    if k == 0 || !x.is_consistent() {
        return Err(Error::check(format!("{k}x{k} average pooling of a {}x{}x{} tensor", x.c, x.h, x.w)));
    }
    let (ho, wo) = (x.h / k, x.w / k);
    let mut out = Chw::zeros(x.c, ho, wo);
    let inv = 1.0 / (k * k) as f32;
    for c in 0..x.c {
        let src = x.plane(c);
        for oy in 0..ho {
            for ox in 0..wo {
                let mut s = 0.0;
                for dy in 0..k {
                    for dx in 0..k {
                        s += src[(oy * k + dy) * x.w + ox * k + dx];
                    }
                }
                out.data[(c * ho + oy) * wo + ox] = s * inv;
            }
        }
    }
    Ok(out)
}

/// InstanceNorm2d(affine = False): per channel, zero mean and unit (biased) variance, eps 1e-5.
pub fn instance_norm(x: &mut Chw) {
    if !x.is_consistent() || x.h * x.w == 0 {
        return;
    }
    let hw = (x.h * x.w) as f64;
    for c in 0..x.c {
        let plane = &mut x.data[c * x.h * x.w..(c + 1) * x.h * x.w];
        let mean = plane.iter().map(|&v| v as f64).sum::<f64>() / hw;
        let var = plane.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / hw;
        let inv = 1.0 / (var + 1e-5).sqrt();
        plane.iter_mut().for_each(|v| *v = ((*v as f64 - mean) * inv) as f32);
    }
}

/// Source index and weight of PyTorch's bilinear resize (align_corners = False).
fn source_index(dst: usize, in_len: usize, out_len: usize) -> (usize, usize, f32) {
    let scale = in_len as f32 / out_len as f32;
    let src = (scale * (dst as f32 + 0.5) - 0.5).max(0.0);
    let i0 = (src.floor() as usize).min(in_len - 1);
    let i1 = (i0 + 1).min(in_len - 1);
    (i0, i1, src - i0 as f32)
}

/// F.interpolate(x, (h, w), mode = "bilinear", align_corners = False).
pub fn resize_bilinear(x: &Chw, h: usize, w: usize) -> Result<Chw> {
    if !x.is_consistent() || (h * w > 0 && x.h * x.w == 0) {
        return Err(Error::check(format!("cannot resize a {}x{}x{} tensor to {h}x{w}", x.c, x.h, x.w)));
    }
    let mut out = Chw::zeros(x.c, h, w);
    if h * w == 0 {
        return Ok(out);
    }
    let xs: Vec<(usize, usize, f32)> = (0..w).map(|i| source_index(i, x.w, w)).collect();
    out.data.par_chunks_mut(h * w).enumerate().for_each(|(c, plane)| {
        let src = x.plane(c);
        for oy in 0..h {
            let (y0, y1, ly) = source_index(oy, x.h, h);
            for (ox, &(x0, x1, lx)) in xs.iter().enumerate() {
                let top = src[y0 * x.w + x0] * (1.0 - lx) + src[y0 * x.w + x1] * lx;
                let bottom = src[y1 * x.w + x0] * (1.0 - lx) + src[y1 * x.w + x1] * lx;
                plane[oy * w + ox] = top * (1.0 - ly) + bottom * ly;
            }
        }
    });
    Ok(out)
}

/// XFeat's `_unfold2d(x, 8)` for one channel: [1, H, W] to [64, H/8, W/8], channel ky*8 + kx.
pub fn space_to_depth8(x: &Chw) -> Result<Chw> {
    if x.c != 1 || !x.is_consistent() {
        return Err(Error::check(format!("space-to-depth of a {}-channel tensor (needs 1)", x.c)));
    }
    let (ho, wo) = (x.h / 8, x.w / 8);
    let mut out = Chw::zeros(64, ho, wo);
    for ky in 0..8 {
        for kx in 0..8 {
            let c = ky * 8 + kx;
            for oy in 0..ho {
                for ox in 0..wo {
                    out.data[(c * ho + oy) * wo + ox] = x.data[(oy * 8 + ky) * x.w + ox * 8 + kx];
                }
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Convolution by definition, for the im2col path to be held to.
    fn conv_reference(x: &Chw, wt: &[f32], cout: usize, k: usize, stride: usize, pad: usize) -> Chw {
        let ho = (x.h + 2 * pad - k) / stride + 1;
        let wo = (x.w + 2 * pad - k) / stride + 1;
        let mut out = Chw::zeros(cout, ho, wo);
        for co in 0..cout {
            for oy in 0..ho {
                for ox in 0..wo {
                    let mut s = 0.0f64;
                    for ci in 0..x.c {
                        for ky in 0..k {
                            for kx in 0..k {
                                let iy = (oy * stride + ky) as isize - pad as isize;
                                let ix = (ox * stride + kx) as isize - pad as isize;
                                if iy >= 0 && ix >= 0 && (iy as usize) < x.h && (ix as usize) < x.w {
                                    s += x.data[(ci * x.h + iy as usize) * x.w + ix as usize] as f64 * wt[((co * x.c + ci) * k + ky) * k + kx] as f64;
                                }
                            }
                        }
                    }
                    out.data[(co * ho + oy) * wo + ox] = s as f32;
                }
            }
        }
        out
    }

    #[test]
    fn conv_matches_definition() {
        let mut rng = crate::util::SplitMix64::new(3);
        for &(cin, cout, h, w, k, stride, pad) in &[(1, 4, 37, 45, 3, 1, 1), (5, 7, 33, 40, 3, 2, 1), (6, 3, 50, 47, 1, 1, 0)] {
            let x = Chw { c: cin, h, w, data: (0..cin * h * w).map(|_| rng.normal() as f32).collect() };
            let wt: Vec<f32> = (0..cout * cin * k * k).map(|_| rng.normal() as f32).collect();
            let a = conv2d(&x, &wt, None, cout, k, stride, pad).unwrap();
            let b = conv_reference(&x, &wt, cout, k, stride, pad);
            assert_eq!((a.c, a.h, a.w), (b.c, b.h, b.w));
            let worst = a.data.iter().zip(&b.data).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
            assert!(worst < 1e-4, "{worst}");
        }
    }

    /// Depthwise convolution by definition, with TensorFlow's SAME padding made explicit.
    fn depthwise_reference(x: &Chw, wt: &[f32], bias: &[f32], k: usize, stride: usize) -> Chw {
        let ((top, _), (left, _)) = (same_padding(x.h, k, stride), same_padding(x.w, k, stride));
        let (ho, wo) = (x.h.div_ceil(stride), x.w.div_ceil(stride));
        let mut out = Chw::zeros(x.c, ho, wo);
        for c in 0..x.c {
            for oy in 0..ho {
                for ox in 0..wo {
                    let mut s = bias[c] as f64;
                    for ky in 0..k {
                        for kx in 0..k {
                            let iy = (oy * stride + ky) as isize - top as isize;
                            let ix = (ox * stride + kx) as isize - left as isize;
                            if iy >= 0 && ix >= 0 && (iy as usize) < x.h && (ix as usize) < x.w {
                                s += x.data[(c * x.h + iy as usize) * x.w + ix as usize] as f64 * wt[(c * k + ky) * k + kx] as f64;
                            }
                        }
                    }
                    out.data[(c * ho + oy) * wo + ox] = s as f32;
                }
            }
        }
        out
    }

    #[test]
    fn same_padding_gives_ceil_n_over_stride_outputs() {
        for n in 1..40 {
            for k in [1, 3, 5] {
                for stride in [1, 2] {
                    let (a, b) = same_padding(n, k, stride);
                    assert!(b == a || b == a + 1, "n {n} k {k} s {stride}: ({a}, {b})");
                    if n + a + b >= k {
                        assert_eq!((n + a + b - k) / stride + 1, n.div_ceil(stride), "n {n} k {k} s {stride}");
                    }
                }
            }
        }
        // TensorFlow: 448 at stride 2 with a 3x3 kernel pads one row, at the bottom
        assert_eq!(same_padding(448, 3, 2), (0, 1));
        assert_eq!(same_padding(447, 3, 2), (1, 1));
        assert_eq!(same_padding(10, 5, 1), (2, 2));
    }

    #[test]
    fn padded_depthwise_conv_matches_definition() {
        let mut rng = crate::util::SplitMix64::new(5);
        for &(c, h, w, k, stride) in &[(3, 17, 20, 3, 1), (4, 16, 15, 3, 2), (2, 11, 12, 5, 2), (5, 9, 13, 5, 1), (1, 5, 5, 5, 2), (2, 1, 1, 3, 1)] {
            let x = Chw { c, h, w, data: (0..c * h * w).map(|_| rng.normal() as f32).collect() };
            let wt: Vec<f32> = (0..c * k * k).map(|_| rng.normal() as f32).collect();
            let bias: Vec<f32> = (0..c).map(|_| rng.normal() as f32).collect();
            let ((t, b), (l, r)) = (same_padding(h, k, stride), same_padding(w, k, stride));
            let got = depthwise_conv2d(&pad(&x, t, b, l, r), &wt, &bias, k, stride).unwrap();
            let want = depthwise_reference(&x, &wt, &bias, k, stride);
            assert_eq!((got.c, got.h, got.w), (want.c, want.h, want.w), "{c}x{h}x{w} k {k} s {stride}");
            let worst = got.data.iter().zip(&want.data).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
            assert!(worst < 1e-5, "{c}x{h}x{w} k {k} s {stride}: {worst}");
        }
        // no channels, and sizes that do not fit
        assert_eq!(depthwise_conv2d(&Chw::zeros(0, 4, 4), &[], &[], 3, 1).unwrap().data.len(), 0);
        assert!(depthwise_conv2d(&Chw::zeros(2, 4, 4), &[0.0; 9], &[0.0; 2], 3, 1).is_err());
        assert!(depthwise_conv2d(&Chw::zeros(1, 2, 4), &[0.0; 9], &[0.0], 3, 1).is_err());
    }

    #[test]
    fn resize_matches_pytorch_on_a_known_case() {
        // torch.nn.functional.interpolate(torch.arange(4.).view(1,1,2,2), (4,4), mode="bilinear")
        let x = Chw { c: 1, h: 2, w: 2, data: vec![0.0, 1.0, 2.0, 3.0] };
        let y = resize_bilinear(&x, 4, 4).unwrap();
        let expected = [0.0, 0.25, 0.75, 1.0, 0.5, 0.75, 1.25, 1.5, 1.5, 1.75, 2.25, 2.5, 2.0, 2.25, 2.75, 3.0];
        assert_eq!(y.data, expected);
    }
}
