//! RANSAC (Fischler & Bolles 1981) for a homography between matched keypoints, with the
//! adaptive stopping rule (iterations N = log(1 - p) / log(1 - w^4) for the best inlier ratio w so
//! far, Hartley & Zisserman §4.7.1) and a local optimisation step after every new best model
//! (LO-RANSAC, Chum, Matas & Kittler 2003: refit on the inliers by least squares, keep it if it
//! gathers more). Sampling is seeded and independent of other pairs, so a pair's result does not
//! depend on the batch it is verified in.

use super::homography::{fit, sample_is_valid, transfer_error2, Homography};
use crate::util::SplitMix64;

/// RANSAC parameters; coordinates and the threshold are in the same units (fractions of the
/// image's long side in the engine).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacParams {
    /// A match is an inlier when its forward transfer error is below this.
    pub threshold: f64,
    /// Most iterations, whatever the adaptive stopping rule allows.
    pub max_iterations: u32,
    /// Stop once a better model would have been found with this probability.
    pub confidence: f64,
    /// Seed of the sampling generator.
    pub seed: u64,
    /// Least-squares refits on the inliers of each new best model.
    pub refine: bool,
}

/// Below this triangle area (twice, in squared threshold units) a sample counts as collinear.
const MIN_SAMPLE_AREA_IN_THRESHOLDS: f64 = 1.0;
/// Least-squares refits of one new best model (each kept only if it gathers more inliers).
const REFINE_ROUNDS: usize = 3;

/// The best homography found and the inlier flag of every correspondence; `None` with fewer than
/// 4 correspondences or when no sample gave a model.
pub fn ransac_homography(src: &[[f64; 2]], dst: &[[f64; 2]], p: &RansacParams) -> Option<(Homography, Vec<bool>)> {
    let n = src.len().min(dst.len());
    if n < 4 {
        return None;
    }
    let t2 = p.threshold * p.threshold;
    let min_area = MIN_SAMPLE_AREA_IN_THRESHOLDS * t2;
    let mut rng = SplitMix64::new(p.seed);
    let mut best: Option<(Homography, usize)> = None;
    let mut bound = p.max_iterations as f64;
    let mut it = 0u32;
    let count = |h: &Homography| (0..n).filter(|&i| transfer_error2(h, src[i], dst[i]) < t2).count();
    while (it as f64) < bound.min(p.max_iterations as f64) {
        it += 1;
        let idx = sample::<4>(&mut rng, n);
        let (s, d) = (idx.map(|i| src[i]), idx.map(|i| dst[i]));
        if !sample_is_valid(&s, &d, min_area) {
            continue;
        }
        let Some(h) = fit(&s, &d) else { continue };
        let c = count(&h);
        if best.is_some_and(|b| c <= b.1) {
            continue;
        }
        let (mut h, mut c) = (h, c);
        if p.refine {
            for _ in 0..REFINE_ROUNDS {
                let (is, ds): (Vec<[f64; 2]>, Vec<[f64; 2]>) =
                    (0..n).filter(|&i| transfer_error2(&h, src[i], dst[i]) < t2).map(|i| (src[i], dst[i])).unzip();
                match fit(&is, &ds) {
                    Some(g) if count(&g) > c => {
                        c = count(&g);
                        h = g;
                    }
                    _ => break,
                }
            }
        }
        best = Some((h, c));
        bound = iterations_for(c as f64 / n as f64, p.confidence, 4);
    }
    let (h, _) = best?;
    let inliers = (0..n).map(|i| transfer_error2(&h, src[i], dst[i]) < t2).collect();
    Some((h, inliers))
}

/// Iterations after which a sample of `size` inliers was drawn with probability `confidence`,
/// for inlier ratio `w` (the adaptive stop of this RANSAC and of the relative pose's).
pub(super) fn iterations_for(w: f64, confidence: f64, size: i32) -> f64 {
    let all = w.powi(size);
    if all >= 1.0 - 1e-12 {
        return 1.0;
    }
    if all <= 0.0 {
        return f64::INFINITY;
    }
    ((1.0 - confidence).ln() / (1.0 - all).ln()).ceil()
}

/// `N` distinct indices below `n` (n >= N): a minimal sample.
pub(super) fn sample<const N: usize>(rng: &mut SplitMix64, n: usize) -> [usize; N] {
    let mut idx = [0usize; N];
    let mut k = 0;
    while k < N {
        let c = rng.below(n);
        if !idx[..k].contains(&c) {
            idx[k] = c;
            k += 1;
        }
    }
    idx
}

/// Brute force: the largest inlier count of any homography through 4 of the correspondences
/// (every valid 4-subset tried). The reference the tests hold RANSAC to; O(n^4).
pub fn best_inliers_exhaustive(src: &[[f64; 2]], dst: &[[f64; 2]], threshold: f64) -> usize {
    let n = src.len().min(dst.len());
    let t2 = threshold * threshold;
    let min_area = MIN_SAMPLE_AREA_IN_THRESHOLDS * t2;
    let mut best = 0;
    for a in 0..n {
        for b in a + 1..n {
            for c in b + 1..n {
                for d in c + 1..n {
                    let idx = [a, b, c, d];
                    let (s, t) = (idx.map(|i| src[i]), idx.map(|i| dst[i]));
                    if !sample_is_valid(&s, &t, min_area) {
                        continue;
                    }
                    if let Some(h) = fit(&s, &t) {
                        best = best.max((0..n).filter(|&i| transfer_error2(&h, src[i], dst[i]) < t2).count());
                    }
                }
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::verify::homography::apply;

    /// `inliers` points moved by a known homography (with noise well below the threshold) and
    /// `outliers` random pairs, shuffled.
    fn scene(inliers: usize, outliers: usize, seed: u64) -> (Vec<[f64; 2]>, Vec<[f64; 2]>, Vec<bool>, Homography) {
        let h: Homography = [0.9, 0.08, 0.05, -0.06, 1.05, 0.02, 0.15, -0.2, 1.0];
        let mut rng = SplitMix64::new(seed);
        let mut rows = Vec::new();
        for i in 0..inliers + outliers {
            let p = [rng.range(0.0, 1.0), rng.range(0.0, 0.75)];
            let truth = i < inliers;
            let q = match truth {
                true => {
                    let m = apply(&h, p).unwrap();
                    [m[0] + rng.range(-0.001, 0.001), m[1] + rng.range(-0.001, 0.001)]
                }
                false => [rng.range(0.0, 1.0), rng.range(0.0, 0.75)],
            };
            rows.push((rng.next_u64(), p, q, truth));
        }
        rows.sort_by_key(|r| r.0);
        (rows.iter().map(|r| r.1).collect(), rows.iter().map(|r| r.2).collect(), rows.iter().map(|r| r.3).collect(), h)
    }

    fn params(refine: bool) -> RansacParams {
        RansacParams { threshold: 0.006, max_iterations: 5000, confidence: 0.9999, seed: 7, refine }
    }

    #[test]
    fn ransac_finds_as_many_inliers_as_the_exhaustive_search() {
        for seed in 0..3 {
            let (src, dst, truth, h) = scene(16, 24, seed);
            let exhaustive = best_inliers_exhaustive(&src, &dst, 0.006);
            assert!(exhaustive >= 16, "the true model's inliers are reachable: {exhaustive}");
            let (g, inl) = ransac_homography(&src, &dst, &params(false)).unwrap();
            assert_eq!(inl.iter().filter(|&&b| b).count(), exhaustive, "seed {seed}");
            // every true inlier is found, and the model is the true one where the points are
            assert!(truth.iter().zip(&inl).all(|(&t, &i)| !t || i));
            for p in [[0.2, 0.2], [0.8, 0.6]] {
                let (a, b) = (apply(&g, p).unwrap(), apply(&h, p).unwrap());
                assert!((a[0] - b[0]).abs() < 0.005 && (a[1] - b[1]).abs() < 0.005);
            }
            let (_, refined) = ransac_homography(&src, &dst, &params(true)).unwrap();
            assert!(refined.iter().filter(|&&b| b).count() >= exhaustive);
        }
    }

    #[test]
    fn results_depend_on_the_seed_only_and_too_few_points_give_none() {
        let (src, dst, _, _) = scene(30, 60, 11);
        let a = ransac_homography(&src, &dst, &params(true)).unwrap();
        let b = ransac_homography(&src, &dst, &params(true)).unwrap();
        assert_eq!(a, b);
        assert!(ransac_homography(&src[..3], &dst[..3], &params(true)).is_none());
        assert!(ransac_homography(&[], &[], &params(true)).is_none());
        // pure noise: a model may exist but gathers few
        let (src, dst, _, _) = scene(0, 60, 3);
        let n = ransac_homography(&src, &dst, &params(true)).map_or(0, |r| r.1.iter().filter(|&&b| b).count());
        assert!(n < 10, "{n} inliers among random pairs");
    }
}
