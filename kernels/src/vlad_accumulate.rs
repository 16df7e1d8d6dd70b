//! The VLAD kernels' CPU twins (of `shaders/vlad_accumulate.wgsl`: `vlad_assign`,
//! `vlad_accumulate`), with the same bindings, loop shape and reductions; `global::vlad`
//! holds the codebook and the f64 definition (`vlad_reference`).

use super::abi::VladParams;
/// Lanes of the shader's per-object workgroup; reductions over dimensions use the same strides.
pub const LANES: usize = 64;
/// Most centres the shader's per-lane state holds.
pub const MAX_CENTRES: usize = 64;

/// Bindings: `p`, `centres` (k x dim), `descriptors` (n x dim), `assignment` (out, n).
/// One invocation per keypoint: the nearest centre (ties to the lower index).
pub fn vlad_assign(p: &VladParams, centres: &[f32], descriptors: &[f32], assignment: &mut [u32]) {
    let (k, d) = (p.centres as usize, p.dim as usize);
    for (i, slot) in assignment.iter_mut().enumerate().take(p.keypoints as usize) {
        let x = &descriptors[i * d..(i + 1) * d];
        let mut best = (f32::INFINITY, 0u32);
        for j in 0..k {
            let c = &centres[j * d..(j + 1) * d];
            let dist: f32 = x.iter().zip(c).map(|(a, b)| (a - b) * (a - b)).sum();
            if dist < best.0 {
                best = (dist, j as u32);
            }
        }
        *slot = best.1;
    }
}

/// Sum of per-lane partial sums by a tree over the lanes: the shader's reduction.
fn tree(mut acc: [f32; LANES]) -> f32 {
    let mut h = LANES / 2;
    while h > 0 {
        for l in 0..h {
            acc[l] += acc[l + h];
        }
        h /= 2;
    }
    acc[0]
}

/// Bindings: `p`, `centres`, `descriptors` (sorted by object), `assignment`, `object_offsets`
/// (objects + 1: object o owns keypoints `offsets[o]..offsets[o + 1]`), `out` (objects x k x dim).
/// One workgroup per object: residual sums, intra-normalisation, optional power
/// normalisation, L2 normalisation. Objects without keypoints stay zero.
pub fn vlad_accumulate(p: &VladParams, centres: &[f32], descriptors: &[f32], assignment: &[u32], object_offsets: &[u32], out: &mut [f32]) {
    let (k, d) = (p.centres as usize, p.dim as usize);
    for o in 0..p.objects as usize {
        let v = &mut out[o * k * d..(o + 1) * k * d];
        v.fill(0.0);
        let (a, b) = (object_offsets[o] as usize, object_offsets[o + 1] as usize);
        if a == b {
            continue;
        }
        for i in a..b {
            let j = assignment[i] as usize;
            for dd in 0..d {
                v[j * d + dd] += descriptors[i * d + dd] - centres[j * d + dd];
            }
        }
        // lane l owns dimensions l, l + LANES, ... of every centre
        for j in (0..k).filter(|_| p.intra_norm != 0) {
            let block = &mut v[j * d..(j + 1) * d];
            let mut acc = [0.0f32; LANES];
            for (dd, x) in block.iter().enumerate() {
                acc[dd % LANES] += x * x;
            }
            let norm = tree(acc).sqrt();
            if norm > 0.0 {
                block.iter_mut().for_each(|x| *x /= norm);
            }
        }
        let mut acc = [0.0f32; LANES];
        for j in 0..k {
            for dd in 0..d {
                let x = &mut v[j * d + dd];
                if p.power_norm != 0 {
                    *x = x.signum() * x.abs().sqrt();
                }
                acc[dd % LANES] += *x * *x;
            }
        }
        let norm = tree(acc).sqrt();
        if norm > 0.0 {
            v.iter_mut().for_each(|x| *x /= norm);
        }
    }
}
