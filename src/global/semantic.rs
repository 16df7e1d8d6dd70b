//! Stage 2a: the SemLook global descriptor ("Edge (Coarse)", `docs/design/method.md` §2.2 and §2.7).
//!
//! label map -> semantic boundary pixels -> exact Euclidean distance transform -> truncation at
//! τ = `truncation` x diagonal -> area resize to `width` x `height`, values in [0, 1]; plus the
//! SSIM window statistics of that small map, so that matching pays only for the cross term.

use crate::config::GlobalConfig;
use crate::error::{Error, Result};
use crate::input::LabelMap;
use semlook_kernels::abi::PoolParams;
use semlook_kernels::ssim::SsimScratch;
use semlook_kernels::{edt, global_pool, semantic_edges, ssim};

/// Scratch buffers of the global encoder, reused across images (one per worker thread).
#[derive(Debug, Default)]
pub struct GlobalScratch {
    labels: Vec<u32>,
    pub(crate) edges: Vec<u32>,
    g: Vec<i32>,
    s: Vec<i32>,
    t: Vec<i32>,
    pub(crate) d2: Vec<u32>,
    ssim: SsimScratch,
}

impl GlobalScratch {
    /// Edge flags of the last encoded image.
    pub fn edges(&self) -> &[u32] {
        &self.edges
    }
    /// Squared distances of the last encoded image.
    pub fn d2(&self) -> &[u32] {
        &self.d2
    }
}

/// Pooling parameters for an image of the given size.
pub fn pool_params(cfg: &GlobalConfig, width: u32, height: u32) -> PoolParams {
    let diag = ((width as f64).powi(2) + (height as f64).powi(2)).sqrt();
    PoolParams {
        src_width: width,
        src_height: height,
        dst_width: cfg.width as u32,
        dst_height: cfg.height as u32,
        tau: (cfg.truncation * diag) as f32,
        frames: 1,
        _pad: [0; 2],
    }
}

/// Encodes one label map: `desc` gets width x height values, `stats` the SSIM window statistics.
/// `used` flags the classes that make edges (see `ClassTable::used_mask`).
pub fn encode_global(
    labels: &LabelMap,
    used: &[bool; 256],
    cfg: &GlobalConfig,
    scratch: &mut GlobalScratch,
    desc: &mut [f32],
    stats: &mut [f32],
) -> Result<()> {
    let (w, h) = (labels.width() as usize, labels.height() as usize);
    if w > edt::MAX_SIDE || h > edt::MAX_SIDE {
        return Err(Error::invalid("label map", format!("{w}x{h} exceeds the {} pixel side limit of the EDT", edt::MAX_SIDE)));
    }
    let n = w * h;
    let used32: [u32; 256] = std::array::from_fn(|c| used[c] as u32);
    semantic_edges::pack_labels(labels.classes(), &mut scratch.labels);
    scratch.edges.resize(n, 0);
    scratch.g.resize(n, 0);
    scratch.s.resize(n, 0);
    scratch.t.resize(n, 0);
    scratch.d2.resize(n, 0);
    semantic_edges::semantic_edges(&scratch.labels, &used32, &mut scratch.edges, w, h);
    edt::edt_columns(&scratch.edges, &mut scratch.g, w, h);
    edt::edt_rows(&scratch.g, &mut scratch.s, &mut scratch.t, &mut scratch.d2, w, h);
    global_pool::global_pool(&pool_params(cfg, w as u32, h as u32), &scratch.d2, desc);
    ssim::ssim_stats(&cfg.ssim_params(), desc, stats, &mut scratch.ssim);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::classes::ClassTable;
    use proptest::prelude::*;

    #[test]
    fn pooled_descriptor_matches_reference_and_has_edges_at_zero() {
        let t = ClassTable::cityscapes();
        let (w, h) = (130u32, 97u32);
        // a building block on road: edges along its border
        let classes = (0..w * h).map(|i| if (30..80).contains(&(i % w)) && (20..60).contains(&(i / w)) { 2 } else { 0 }).collect();
        let lm = LabelMap::new(w, h, classes, &t).unwrap();
        let cfg = GlobalConfig::default();
        let p = cfg.ssim_params();
        let (mut d, mut s) = (vec![0.0; p.len()], vec![0.0; p.stats_len()]);
        let mut scratch = GlobalScratch::default();
        encode_global(&lm, &t.used_mask(), &cfg, &mut scratch, &mut d, &mut s).unwrap();
        let reference = global_pool::global_pool_reference(&pool_params(&cfg, w, h), &scratch.d2);
        for (a, b) in d.iter().zip(&reference) {
            assert!((*a as f64 - b).abs() < 1e-5, "{a} vs {b}");
        }
        assert!(d.iter().all(|v| (0.0..=1.0).contains(v)));
        assert!(d.contains(&1.0) && d.iter().any(|&v| v < 0.2));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(40))]
        /// Fast SSIM with precomputed stats equals the windowed definition; SSIM(x, x) = 1.
        #[test]
        fn ssim_equals_definition(seed in any::<u64>(), win in prop::sample::select(vec![3usize, 5, 7])) {
            let cfg = GlobalConfig { width: 16, height: 12, ssim_window: win, ..Default::default() };
            let p = cfg.ssim_params();
            let mut rng = crate::util::SplitMix64::new(seed);
            let x: Vec<f32> = (0..p.len()).map(|_| rng.next_f64() as f32).collect();
            let y: Vec<f32> = x.iter().map(|v| v * 0.7 + 0.3 * rng.next_f64() as f32).collect();
            let mut sc = SsimScratch::default();
            let (mut sx, mut sy) = (vec![0.0; p.stats_len()], vec![0.0; p.stats_len()]);
            ssim::ssim_stats(&p, &x, &mut sx, &mut sc);
            ssim::ssim_stats(&p, &y, &mut sy, &mut sc);
            let fast = ssim::ssim_pair(&p, &x, &sx, &y, &sy, &mut sc) as f64;
            prop_assert!((fast - ssim::ssim_reference(&p, &x, &y)).abs() < 1e-4);
            prop_assert!((ssim::ssim_pair(&p, &x, &sx, &x, &sx, &mut sc) - 1.0).abs() < 1e-4);
        }
    }
}
