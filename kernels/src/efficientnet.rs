//! The CPU twins of `shaders/efficientnet.wgsl` (EfficientNet-Lite + GeM, the whole-image
//! embedding, on the device): the same entry points under the same names, the same bindings
//! (arguments, in binding order) and the same loop shape (a loop over the dispatch's invocations,
//! the shader's body inside; `pointwise` per workgroup, its phases between barriers each a loop
//! over the workgroup's invocations). semlook's native pass (`networks::embedding`) runs its own
//! fast ops, which the tests hold to these twins; the device is held to them too.

use super::abi::{EffConvParams, EffPointParams, GemParams};

/// Lanes of `conv_direct`'s and `gem_pool`'s workgroups.
pub const LANES: usize = 256;
/// `pointwise`'s tile side (pixels x output channels per workgroup, input channels per pass).
pub const TILE: usize = 16;
/// GeM's floor: inputs below it count as it.
pub const GEM_FLOOR: f32 = 1e-6;

/// `conv_direct`: output value i of `cp` for every invocation of a (`row` x any) grid of LANES.
pub fn conv_direct(cp: &EffConvParams, conv_in: &[f32], conv_w: &[f32], conv_b: &[f32], conv_out: &mut [f32]) {
    let u = |v: u32| v as usize;
    let (n, plane) = (u(cp.n), u(cp.ho) * u(cp.wo));
    for i in 0..n {
        let co = i / plane;
        let (oy, ox) = ((i % plane) / u(cp.wo), i % u(cp.wo));
        let (c0, c1) = if cp.depthwise == 1 { (co, co + 1) } else { (0, u(cp.cin)) };
        let k = u(cp.k);
        let mut s = conv_b[co];
        for ci in c0..c1 {
            let wbase = (co * (c1 - c0) + (ci - c0)) * k * k;
            for ky in 0..k {
                let iy = (oy * u(cp.stride) + ky) as i64 - cp.pad_top as i64;
                if iy < 0 || iy >= cp.h as i64 {
                    continue;
                }
                for kx in 0..k {
                    let ix = (ox * u(cp.stride) + kx) as i64 - cp.pad_left as i64;
                    if ix < 0 || ix >= cp.w as i64 {
                        continue;
                    }
                    let v = conv_in[(ci * u(cp.h) + iy as usize) * u(cp.w) + ix as usize] * cp.scale + cp.shift;
                    s += conv_w[wbase + ky * k + kx] * v;
                }
            }
        }
        if cp.relu6 == 1 {
            s = s.clamp(0.0, 6.0);
        }
        conv_out[i] = s;
    }
}

/// `pointwise`: every workgroup (ceil(hw / TILE) x ceil(cout / TILE)) of TILE x TILE invocations.
pub fn pointwise(pp: &EffPointParams, pw_in: &[f32], pw_w: &[f32], pw_b: &[f32], pw_res: &[f32], pw_out: &mut [f32]) {
    let u = |v: u32| v as usize;
    let (cin, cout, hw) = (u(pp.cin), u(pp.cout), u(pp.hw));
    let mut tile_in = [0.0f32; TILE * TILE];
    let mut tile_w = [0.0f32; TILE * TILE];
    for wy in 0..cout.div_ceil(TILE) {
        for wx in 0..hw.div_ceil(TILE) {
            let mut s = [0.0f32; TILE * TILE];
            for c0 in (0..cin).step_by(TILE) {
                for ly in 0..TILE {
                    for lx in 0..TILE {
                        let (ci_in, p_in) = (c0 + ly, wx * TILE + lx);
                        tile_in[ly * TILE + lx] = if ci_in < cin && p_in < hw { pw_in[ci_in * hw + p_in] } else { 0.0 };
                        let (co_w, ci_w) = (wy * TILE + ly, c0 + lx);
                        tile_w[ly * TILE + lx] = if co_w < cout && ci_w < cin { pw_w[co_w * cin + ci_w] } else { 0.0 };
                    }
                }
                let n = TILE.min(cin - c0);
                for ly in 0..TILE {
                    for lx in 0..TILE {
                        for ci in 0..n {
                            s[ly * TILE + lx] += tile_w[ly * TILE + ci] * tile_in[ci * TILE + lx];
                        }
                    }
                }
            }
            for ly in 0..TILE {
                for lx in 0..TILE {
                    let (p, co) = (wx * TILE + lx, wy * TILE + ly);
                    if p < hw && co < cout {
                        let mut v = s[ly * TILE + lx] + pw_b[co];
                        if pp.relu6 == 1 {
                            v = v.clamp(0.0, 6.0);
                        }
                        if pp.residual == 1 {
                            v += pw_res[co * hw + p];
                        }
                        pw_out[co * hw + p] = v;
                    }
                }
            }
        }
    }
}

/// `gem_pool`: one invocation per channel.
pub fn gem_pool(gp: &GemParams, gem_in: &[f32], gem_out: &mut [f32]) {
    let (c, hw) = (gp.c as usize, gp.hw as usize);
    for (ch, out) in gem_out.iter_mut().enumerate().take(c) {
        let mut s = 0.0f32;
        for i in 0..hw {
            let v = gem_in[ch * hw + i].max(GEM_FLOOR);
            s += v * v * v;
        }
        *out = (s / hw as f32).powf(1.0 / 3.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    /// A convolution by definition in f64 (full or depthwise, TF SAME given as pads).
    fn conv_reference(cp: &EffConvParams, x: &[f32], w: &[f32], b: &[f32]) -> Vec<f64> {
        let u = |v: u32| v as usize;
        let mut out = vec![0.0f64; u(cp.n)];
        for co in 0..u(cp.cout) {
            for oy in 0..u(cp.ho) {
                for ox in 0..u(cp.wo) {
                    let mut s = b[co] as f64;
                    let chans: Vec<usize> = if cp.depthwise == 1 { vec![co] } else { (0..u(cp.cin)).collect() };
                    for (j, &ci) in chans.iter().enumerate() {
                        for ky in 0..u(cp.k) {
                            for kx in 0..u(cp.k) {
                                let iy = (oy * u(cp.stride) + ky) as i64 - cp.pad_top as i64;
                                let ix = (ox * u(cp.stride) + kx) as i64 - cp.pad_left as i64;
                                if iy >= 0 && ix >= 0 && iy < cp.h as i64 && ix < cp.w as i64 {
                                    let v = x[(ci * u(cp.h) + iy as usize) * u(cp.w) + ix as usize] as f64 * cp.scale as f64 + cp.shift as f64;
                                    s += w[((co * chans.len() + j) * u(cp.k) + ky) * u(cp.k) + kx] as f64 * v;
                                }
                            }
                        }
                    }
                    out[(co * u(cp.ho) + oy) * u(cp.wo) + ox] = if cp.relu6 == 1 { s.clamp(0.0, 6.0) } else { s };
                }
            }
        }
        out
    }

    #[test]
    fn conv_direct_is_the_padded_convolution() {
        let mut rng = SplitMix64::new(9);
        for &(cin, h, w, k, stride, depthwise) in &[
            (3usize, 9usize, 12usize, 3usize, 2usize, false),
            (4, 8, 7, 3, 1, true),
            (5, 10, 11, 5, 2, true),
            (2, 1, 1, 3, 1, false),
            (0, 4, 4, 3, 1, true),
        ] {
            let cout = if depthwise { cin } else { 6 };
            let (ho, wo) = (h.div_ceil(stride), w.div_ceil(stride));
            let cp = EffConvParams {
                cin: cin as u32,
                cout: cout as u32,
                h: h as u32,
                w: w as u32,
                ho: ho as u32,
                wo: wo as u32,
                k: k as u32,
                stride: stride as u32,
                // any pads: the twin is held to the reference at the pads it is given (which
                // pads SAME means is the network's rule, `semlook::nn::conv::same_padding`);
                // uneven ones at stride 2
                pad_top: (k / 2) as u32,
                pad_left: (k / 2).saturating_sub(stride - 1) as u32,
                depthwise: depthwise as u32,
                relu6: 1,
                scale: 1.0 / 128.0,
                shift: -127.0 / 128.0,
                row: 1,
                n: (cout * ho * wo) as u32,
            };
            let x: Vec<f32> = (0..cin * h * w).map(|_| (rng.normal() * 80.0 + 127.0) as f32).collect();
            let per = if depthwise { 1 } else { cin };
            let wt: Vec<f32> = (0..cout * per * k * k).map(|_| rng.normal() as f32 * 0.3).collect();
            let b: Vec<f32> = (0..cout).map(|_| rng.normal() as f32).collect();
            let mut got = vec![f32::NAN; cout * ho * wo];
            conv_direct(&cp, &x, &wt, &b, &mut got);
            let want = conv_reference(&cp, &x, &wt, &b);
            let worst = got.iter().zip(&want).map(|(g, w)| (*g as f64 - w).abs()).fold(0.0, f64::max);
            assert!(worst < 1e-4, "{cin} {h}x{w} k {k} s {stride} dw {depthwise}: {worst}");
        }
    }

    #[test]
    fn pointwise_is_the_matrix_product_with_its_epilogue() {
        let mut rng = SplitMix64::new(10);
        for &(cin, cout, hw, relu6, residual) in &[(3, 5, 7, 1, 0), (17, 33, 40, 0, 1), (16, 16, 16, 1, 1), (0, 4, 5, 0, 0), (4, 0, 5, 1, 0)] {
            let pp = EffPointParams { cin, cout, hw, relu6, residual, _pad: [0; 3] };
            let (ci, co, n) = (cin as usize, cout as usize, hw as usize);
            let x: Vec<f32> = (0..ci * n).map(|_| rng.normal() as f32).collect();
            let w: Vec<f32> = (0..co * ci).map(|_| rng.normal() as f32).collect();
            let b: Vec<f32> = (0..co).map(|_| rng.normal() as f32).collect();
            let r: Vec<f32> = (0..co * n).map(|_| rng.normal() as f32).collect();
            let mut got = vec![f32::NAN; co * n];
            pointwise(&pp, &x, &w, &b, &r, &mut got);
            for o in 0..co {
                for p in 0..n {
                    let mut v = b[o] as f64 + (0..ci).map(|c| w[o * ci + c] as f64 * x[c * n + p] as f64).sum::<f64>();
                    if relu6 == 1 {
                        v = v.clamp(0.0, 6.0);
                    }
                    if residual == 1 {
                        v += r[o * n + p] as f64;
                    }
                    assert!((got[o * n + p] as f64 - v).abs() < 1e-4, "{cin}x{cout}x{hw}: ({o}, {p})");
                }
            }
        }
    }

    #[test]
    fn gem_pool_is_the_generalised_mean() {
        let x = [0.0f32, 1.0, 2.0, -3.0, 8.0, 8.0, 8.0, 8.0];
        let mut out = [f32::NAN; 2];
        gem_pool(&GemParams { c: 2, hw: 4, _pad: [0; 2] }, &x, &mut out);
        let first = ((0.0 + 1.0 + 8.0 + 0.0) / 4.0f64).cbrt();
        assert!((out[0] as f64 - first).abs() < 1e-6 && (out[1] - 8.0).abs() < 1e-5, "{out:?}");
        gem_pool(&GemParams { c: 0, hw: 4, _pad: [0; 2] }, &x, &mut out[..0]);
    }
}
