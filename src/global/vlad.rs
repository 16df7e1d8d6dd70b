//! VLAD per object (Jégou, Douze, Schmid & Pérez, CVPR 2010; `docs/design/method.md` §2.4): each keypoint inside an
//! object is assigned to its nearest codebook centre, residuals are summed per centre, each
//! centre's sum is L2-normalised (intra-normalisation), optionally power-normalised, and the
//! concatenation is L2-normalised. Here: that definition (`vlad_reference`, in f64) and the
//! codebook, trained by k-means with k-means++ seeding; the kernels' CPU twins are in
//! `semlook_kernels::vlad_accumulate` (named after `shaders/vlad_accumulate.wgsl`).

use crate::error::{Error, Result};
use crate::util::SplitMix64;

/// The normalisations of a VLAD vector (method.md §2.4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct VladNorm {
    /// L2 per centre (intra-normalisation).
    pub intra: bool,
    /// Signed square root before the final L2.
    pub power: bool,
}

impl VladNorm {
    /// The normalisations `[appearance]` asks for (`intra_norm`, `power_norm`).
    pub fn from_config(a: &crate::config::AppearanceConfig) -> Self {
        VladNorm { intra: a.intra_norm, power: a.power_norm }
    }
}

/// Reference: VLAD of one object straight from the definition, in f64.
pub fn vlad_reference(centres: &[f32], k: usize, d: usize, descriptors: &[&[f32]], norm: VladNorm) -> Vec<f64> {
    let mut v = vec![0.0f64; k * d];
    if k == 0 || centres.len() < k * d || descriptors.iter().any(|x| x.len() < d) {
        return v;
    }
    for x in descriptors {
        let j = (0..k)
            .min_by(|&a, &b| {
                let da: f64 = (0..d).map(|t| (x[t] as f64 - centres[a * d + t] as f64).powi(2)).sum();
                let db: f64 = (0..d).map(|t| (x[t] as f64 - centres[b * d + t] as f64).powi(2)).sum();
                da.total_cmp(&db)
            })
            .unwrap_or(0); // k >= 1 (checked above)
        for t in 0..d {
            v[j * d + t] += x[t] as f64 - centres[j * d + t] as f64;
        }
    }
    for j in (0..k).filter(|_| norm.intra) {
        let n = v[j * d..(j + 1) * d].iter().map(|x| x * x).sum::<f64>().sqrt();
        if n > 0.0 {
            v[j * d..(j + 1) * d].iter_mut().for_each(|x| *x /= n);
        }
    }
    if norm.power {
        v.iter_mut().for_each(|x| *x = x.signum() * x.abs().sqrt());
    }
    let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    if n > 0.0 {
        v.iter_mut().for_each(|x| *x /= n);
    }
    v
}

/// A VLAD codebook: `k` centres of `dim` values.
#[derive(Debug, Clone, PartialEq)]
pub struct Codebook {
    /// Number of centres.
    pub k: usize,
    /// Length of a centre (the descriptors' dimension).
    pub dim: usize,
    /// The centres, `dim` values each, one after another (k x dim).
    pub centres: Vec<f32>,
}

impl Codebook {
    /// The codebook as a map stores it: a safetensors file with one f32 tensor `centres` [k, dim].
    pub fn file_bytes(&self) -> Result<Vec<u8>> {
        let bad =
            |e: safetensors::SafeTensorError| Error::check(format!("codebook of {} x {} with {} values: {e}", self.k, self.dim, self.centres.len()));
        let centres =
            safetensors::tensor::TensorView::new(safetensors::tensor::Dtype::F32, vec![self.k, self.dim], bytemuck::cast_slice(&self.centres))
                .map_err(bad)?;
        safetensors::serialize([("centres", centres)], None).map_err(bad)
    }
    /// SHA-256 of [`Codebook::file_bytes`]: names the codebook in maps and descriptor sets.
    pub fn sha256(&self) -> Result<String> {
        Ok(crate::util::sha256_hex(&self.file_bytes()?))
    }
}

/// k-means (Lloyd) with k-means++ seeding (Arthur & Vassilvitskii 2007), deterministic from
/// `seed`. `samples` holds `dim` values per sample; needs at least `k` samples.
pub fn train_codebook(samples: &[f32], dim: usize, k: usize, iterations: usize, seed: u64) -> Result<Codebook> {
    let n = samples.len().checked_div(dim).unwrap_or(0);
    if n < k || k == 0 {
        return Err(Error::check(format!("{n} descriptors cannot train {k} centres")));
    }
    let x = |i: usize| &samples[i * dim..(i + 1) * dim];
    let dist2 = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(p, q)| (p - q) * (p - q)).sum::<f32>();
    let mut rng = SplitMix64::new(seed);
    let mut centres: Vec<f32> = x(rng.below(n)).to_vec();
    let mut nearest: Vec<f32> = (0..n).map(|i| dist2(x(i), &centres[..dim])).collect();
    while centres.len() < k * dim {
        let total: f64 = nearest.iter().map(|&v| v as f64).sum();
        let pick = if total <= 0.0 {
            rng.below(n)
        } else {
            let mut r = rng.next_f64() * total;
            let mut i = 0;
            while i + 1 < n && r >= nearest[i] as f64 {
                r -= nearest[i] as f64;
                i += 1;
            }
            i
        };
        let c = x(pick).to_vec();
        for (i, d) in nearest.iter_mut().enumerate() {
            *d = d.min(dist2(x(i), &c));
        }
        centres.extend(c);
    }
    let mut assign = vec![0usize; n];
    for _ in 0..iterations {
        let mut changed = false;
        for (i, a) in assign.iter_mut().enumerate() {
            let best = (0..k)
                .min_by(|&p, &q| dist2(x(i), &centres[p * dim..(p + 1) * dim]).total_cmp(&dist2(x(i), &centres[q * dim..(q + 1) * dim])))
                .unwrap_or(0); // k >= 1
            changed |= *a != best;
            *a = best;
        }
        let mut sums = vec![0.0f64; k * dim];
        let mut counts = vec![0usize; k];
        for (i, &a) in assign.iter().enumerate() {
            counts[a] += 1;
            for t in 0..dim {
                sums[a * dim + t] += x(i)[t] as f64;
            }
        }
        for j in 0..k {
            if counts[j] == 0 {
                // an empty cluster takes the sample farthest from its centre
                let far = (0..n)
                    .max_by(|&p, &q| dist2(x(p), &centres[assign[p] * dim..][..dim]).total_cmp(&dist2(x(q), &centres[assign[q] * dim..][..dim])))
                    .unwrap_or(0); // n >= k >= 1
                centres[j * dim..(j + 1) * dim].copy_from_slice(x(far));
                changed = true;
            } else {
                for t in 0..dim {
                    centres[j * dim + t] = (sums[j * dim + t] / counts[j] as f64) as f32;
                }
            }
        }
        if !changed {
            break;
        }
    }
    Ok(Codebook { k, dim, centres })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use semlook_kernels::abi::VladParams;
    use semlook_kernels::vlad_accumulate::{vlad_accumulate, vlad_assign};

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(60))]
        /// The twin's VLAD equals the definition on random objects, with and without power norm.
        #[test]
        fn vlad_equals_definition(seed in any::<u64>(), k in 1usize..6, d in 1usize..70, objects in 1usize..5, power in any::<bool>(), intra in any::<bool>()) {
            let mut rng = SplitMix64::new(seed);
            let centres: Vec<f32> = (0..k * d).map(|_| rng.normal() as f32).collect();
            let counts: Vec<usize> = (0..objects).map(|_| rng.below(6)).collect();
            let n: usize = counts.iter().sum();
            let descs: Vec<f32> = (0..n * d).map(|_| rng.normal() as f32).collect();
            let mut offsets = vec![0u32];
            for c in &counts { offsets.push(offsets.last().unwrap() + *c as u32); }
            let norm = VladNorm { intra, power };
            let p = VladParams { centres: k as u32, dim: d as u32, keypoints: n as u32, objects: objects as u32, power_norm: power as u32, intra_norm: intra as u32, _pad: [0; 2] };
            let mut assign = vec![0u32; n];
            vlad_assign(&p, &centres, &descs, &mut assign);
            let mut out = vec![0.0f32; objects * k * d];
            vlad_accumulate(&p, &centres, &descs, &assign, &offsets, &mut out);
            for o in 0..objects {
                let (a, b) = (offsets[o] as usize, offsets[o + 1] as usize);
                let mine: Vec<&[f32]> = (a..b).map(|i| &descs[i * d..(i + 1) * d]).collect();
                let r = vlad_reference(&centres, k, d, &mine, norm);
                for (x, y) in out[o * k * d..(o + 1) * k * d].iter().zip(&r) {
                    prop_assert!((*x as f64 - y).abs() < 1e-4, "{x} vs {y}");
                }
            }
        }
    }

    #[test]
    fn kmeans_finds_separated_clusters_deterministically() {
        let mut rng = SplitMix64::new(9);
        let mut s = Vec::new();
        for c in [[0.0f32, 0.0], [10.0, 0.0], [0.0, 10.0]] {
            for _ in 0..50 {
                s.extend([c[0] + rng.normal() as f32 * 0.1, c[1] + rng.normal() as f32 * 0.1]);
            }
        }
        let a = train_codebook(&s, 2, 3, 20, 5).unwrap();
        assert_eq!(a, train_codebook(&s, 2, 3, 20, 5).unwrap());
        let mut found: Vec<(i32, i32)> = a.centres.chunks(2).map(|c| (c[0].round() as i32, c[1].round() as i32)).collect();
        found.sort();
        assert_eq!(found, vec![(0, 0), (0, 10), (10, 0)]);
        assert!(train_codebook(&s[..4], 2, 3, 5, 1).is_err());
    }
}
