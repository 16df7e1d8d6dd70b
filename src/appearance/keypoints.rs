//! SuperPoint-style keypoint decoding of a network's cell outputs (DeTone, Malisiewicz &
//! Rabinovich, "SuperPoint", CVPRW 2018; the same layout as XFeat's keypoint head): per 8x8 cell a
//! softmax over 65 logits, the "no keypoint" dustbin dropped, the 64 probabilities shuffled to
//! full resolution; the score is that probability times the reliability map (when the network
//! has one); then non-maximum suppression, a threshold, the best N, and descriptors sampled
//! bilinearly from the dense map and L2-normalised.

use crate::error::{Error, Result};
use crate::networks::NetOutputs;
use crate::nn::conv::Chw;

/// Parameters of keypoint decoding: suppression radius, score threshold, keypoint budget, border.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeypointParams {
    /// Keep a pixel only if no pixel within this Chebyshev radius scores higher.
    pub nms_radius: usize,
    /// Keep only pixels scoring above this (for [`detect`], the heatmap alone).
    pub threshold: f32,
    /// Most keypoints kept, best first.
    pub max_keypoints: usize,
    /// Ignore keypoints this close to the image border (pixels).
    pub border: usize,
}

impl KeypointParams {
    /// The decoding of the appearance keypoints (`[appearance]`: VLAD's keypoints when
    /// `sampling = "keypoints"`).
    pub fn appearance(cfg: &crate::config::AppearanceConfig) -> KeypointParams {
        KeypointParams { nms_radius: cfg.nms_radius, threshold: cfg.score_threshold as f32, max_keypoints: cfg.max_keypoints, border: cfg.border }
    }

    /// The detection of the stored verification keypoints (`[keypoints]`); `None` when a map
    /// stores none.
    pub fn verification(cfg: &crate::config::KeypointsConfig) -> Option<KeypointParams> {
        (cfg.stored > 0).then_some(KeypointParams {
            nms_radius: cfg.nms_radius,
            threshold: cfg.score_threshold as f32,
            max_keypoints: cfg.stored,
            border: cfg.border,
        })
    }
}

/// Keypoints of one image, in the coordinates of the network input.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Keypoints {
    /// (x, y) per keypoint, in pixels.
    pub xy: Vec<[f32; 2]>,
    /// Score per keypoint: probability times reliability (dense cells: the reliability, or 1).
    pub scores: Vec<f32>,
    /// `dim` values per keypoint, unit length.
    pub descriptors: Vec<f32>,
    /// Length of a descriptor.
    pub dim: usize,
}

impl Keypoints {
    /// Number of keypoints.
    pub fn len(&self) -> usize {
        self.xy.len()
    }
    /// Whether there are no keypoints.
    pub fn is_empty(&self) -> bool {
        self.xy.is_empty()
    }
}

/// Bilinear sample of every channel of a 1/8-resolution map at full-resolution pixel (x, y),
/// treating cell centres as sample points.
fn sample(map: &Chw, x: f32, y: f32, out: &mut [f32]) {
    let fx = ((x + 0.5) / 8.0 - 0.5).clamp(0.0, (map.w - 1) as f32);
    let fy = ((y + 0.5) / 8.0 - 0.5).clamp(0.0, (map.h - 1) as f32);
    let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(map.w - 1), (y0 + 1).min(map.h - 1));
    let (lx, ly) = (fx - x0 as f32, fy - y0 as f32);
    for (c, o) in out.iter_mut().enumerate() {
        let p = map.plane(c);
        let top = p[y0 * map.w + x0] * (1.0 - lx) + p[y0 * map.w + x1] * lx;
        let bottom = p[y1 * map.w + x0] * (1.0 - lx) + p[y1 * map.w + x1] * lx;
        *o = top * (1.0 - ly) + bottom * ly;
    }
}

/// The keypoint heatmap at full resolution (H x W = 8h x 8w): per 8x8 cell a softmax over its
/// 65 logits, the dustbin dropped, the 64 probabilities in the cell's pixels.
pub fn heatmap(l: &Chw) -> Result<(Vec<f32>, usize, usize)> {
    if l.c != 65 || !l.is_consistent() {
        return Err(Error::check(format!("keypoint logits are {}x{}x{} (need 65 channels)", l.c, l.h, l.w)));
    }
    let (h, w) = (l.h, l.w);
    let (hh, ww) = (h * 8, w * 8);
    let mut scores = vec![0.0f32; hh * ww];
    let cell = h * w;
    let mut e = [0.0f32; 65];
    for cy in 0..h {
        for cx in 0..w {
            let i = cy * w + cx;
            let m = (0..65).map(|c| l.data[c * cell + i]).fold(f32::NEG_INFINITY, f32::max);
            for (c, v) in e.iter_mut().enumerate() {
                *v = (l.data[c * cell + i] - m).exp();
            }
            let sum: f32 = e.iter().sum();
            for k in 0..64 {
                let (ky, kx) = (k / 8, k % 8);
                scores[(cy * 8 + ky) * ww + cx * 8 + kx] = e[k] / sum;
            }
        }
    }
    Ok((scores, hh, ww))
}

/// Full-resolution score map (H x W = 8h x 8w) from the cell logits and reliability; fails
/// when the outputs are not SuperPoint's layout.
pub fn score_map(out: &NetOutputs) -> Result<(Vec<f32>, usize, usize)> {
    let rel_ok = out.reliability.as_ref().is_none_or(|r| r.c == 1 && r.h > 0 && r.w > 0 && r.is_consistent());
    if !rel_ok {
        return Err(Error::check("the reliability map is not one channel"));
    }
    let (mut scores, hh, ww) = heatmap(&out.logits)?;
    if let Some(rel) = &out.reliability {
        let mut v = [0.0f32];
        for y in 0..hh {
            for x in 0..ww {
                sample(rel, x as f32, y as f32, &mut v);
                scores[y * ww + x] *= v[0];
            }
        }
    }
    Ok((scores, hh, ww))
}

/// Decodes keypoints and descriptors from network outputs.
pub fn extract(out: &NetOutputs, p: &KeypointParams) -> Result<Keypoints> {
    let d = &out.descriptors;
    if d.c == 0 || d.h == 0 || d.w == 0 || !d.is_consistent() {
        return Err(Error::check(format!("descriptor map is {}x{}x{}", d.c, d.h, d.w)));
    }
    let (scores, hh, ww) = score_map(out)?;
    // separable max filter of radius r
    let r = p.nms_radius;
    let mut rowmax = vec![0.0f32; hh * ww];
    for y in 0..hh {
        for x in 0..ww {
            let (a, b) = (x.saturating_sub(r), (x + r).min(ww - 1));
            rowmax[y * ww + x] = scores[y * ww + a..=y * ww + b].iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
        }
    }
    let mut cand: Vec<(f32, usize)> = Vec::new();
    for y in p.border..hh.saturating_sub(p.border) {
        for x in p.border..ww.saturating_sub(p.border) {
            let s = scores[y * ww + x];
            if s <= p.threshold {
                continue;
            }
            let (a, b) = (y.saturating_sub(r), (y + r).min(hh - 1));
            let local = (a..=b).map(|yy| rowmax[yy * ww + x]).fold(f32::NEG_INFINITY, f32::max);
            if s >= local {
                cand.push((s, y * ww + x));
            }
        }
    }
    cand.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    cand.truncate(p.max_keypoints);
    // unit-length dense descriptors, sampled, then normalised again
    let dim = d.c;
    let mut dense = d.clone();
    let cell = d.h * d.w;
    for i in 0..cell {
        let n = (0..dim).map(|c| dense.data[c * cell + i].powi(2)).sum::<f32>().sqrt().max(1e-12);
        for c in 0..dim {
            dense.data[c * cell + i] /= n;
        }
    }
    let mut k = Keypoints { dim, ..Default::default() };
    let mut v = vec![0.0f32; dim];
    for (s, i) in cand {
        let (x, y) = ((i % ww) as f32, (i / ww) as f32);
        sample(&dense, x, y, &mut v);
        let n = v.iter().map(|a| a * a).sum::<f32>().sqrt().max(1e-12);
        k.descriptors.extend(v.iter().map(|a| a / n));
        k.xy.push([x, y]);
        k.scores.push(s);
    }
    Ok(k)
}

/// XFeat's own detector (`detectAndCompute`, Potje et al. 2024): non-maximum suppression of the
/// keypoint heatmap alone (softmax over each cell's 65 logits, dustbin dropped), the survivors
/// above the threshold scored heatmap x reliability (bilinear at the keypoint), the best N kept
/// (ties to the earlier pixel in raster order), descriptors sampled bilinearly from the unit-length
/// dense map and normalised again. What the verification stores: unlike [`extract`], the
/// reliability does not take part in the suppression, as in XFeat.
pub fn detect(out: &NetOutputs, p: &KeypointParams) -> Result<Keypoints> {
    let d = &out.descriptors;
    if d.c == 0 || d.h == 0 || d.w == 0 || !d.is_consistent() {
        return Err(Error::check(format!("descriptor map is {}x{}x{}", d.c, d.h, d.w)));
    }
    let (heat, hh, ww) = heatmap(&out.logits)?;
    let r = p.nms_radius;
    let mut rel = [1.0f32];
    let mut cand: Vec<(f32, usize)> = Vec::new();
    for y in p.border..hh.saturating_sub(p.border) {
        for x in p.border..ww.saturating_sub(p.border) {
            let h = heat[y * ww + x];
            if h <= p.threshold {
                continue;
            }
            // a local maximum of its (2r + 1)^2 window (few pixels pass the threshold)
            let (x0, x1) = (x.saturating_sub(r), (x + r).min(ww - 1));
            if (y.saturating_sub(r)..=(y + r).min(hh - 1)).any(|yy| heat[yy * ww + x0..=yy * ww + x1].iter().any(|&v| v > h)) {
                continue;
            }
            if let Some(rm) = &out.reliability {
                sample(rm, x as f32, y as f32, &mut rel);
            }
            cand.push((h * rel[0], y * ww + x));
        }
    }
    cand.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    cand.truncate(p.max_keypoints);
    let dim = d.c;
    let cells = d.h * d.w;
    let mut k = Keypoints { dim, ..Default::default() };
    let (mut v, mut cell) = (vec![0.0f32; dim], vec![0.0f32; 4 * dim]);
    for (s, i) in cand {
        let (x, y) = ((i % ww) as f32, (i / ww) as f32);
        // bilinear of the four unit-length cell descriptors around the point
        let fx = ((x + 0.5) / 8.0 - 0.5).clamp(0.0, (d.w - 1) as f32);
        let fy = ((y + 0.5) / 8.0 - 0.5).clamp(0.0, (d.h - 1) as f32);
        let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(d.w - 1), (y0 + 1).min(d.h - 1));
        let (lx, ly) = (fx - x0 as f32, fy - y0 as f32);
        for (corner, &c) in [y0 * d.w + x0, y0 * d.w + x1, y1 * d.w + x0, y1 * d.w + x1].iter().enumerate() {
            let dst = &mut cell[corner * dim..(corner + 1) * dim];
            for (ch, o) in dst.iter_mut().enumerate() {
                *o = d.data[ch * cells + c];
            }
            let n = dst.iter().map(|a| a * a).sum::<f32>().sqrt().max(1e-12);
            dst.iter_mut().for_each(|a| *a /= n);
        }
        for (ch, o) in v.iter_mut().enumerate() {
            let top = cell[ch] * (1.0 - lx) + cell[dim + ch] * lx;
            let bottom = cell[2 * dim + ch] * (1.0 - lx) + cell[3 * dim + ch] * lx;
            *o = top * (1.0 - ly) + bottom * ly;
        }
        let n = v.iter().map(|a| a * a).sum::<f32>().sqrt().max(1e-12);
        k.descriptors.extend(v.iter().map(|a| a / n));
        k.xy.push([x, y]);
        k.scores.push(s);
    }
    Ok(k)
}

/// Dense sampling: the descriptor of every cell of the 1/8-resolution map, L2-normalised, at the
/// cell's centre in network-input pixels (where `sample` reads the cell exactly), scored by the
/// reliability there (1 without one). Cells in raster order.
pub fn dense(out: &NetOutputs) -> Keypoints {
    let d = &out.descriptors;
    let (dim, cells) = (d.c, d.h * d.w);
    let mut k = Keypoints { dim, ..Default::default() };
    if !d.is_consistent() {
        return k;
    }
    k.descriptors.reserve(dim * cells);
    for i in 0..cells {
        let n = (0..dim).map(|c| d.data[c * cells + i].powi(2)).sum::<f32>().sqrt().max(1e-12);
        k.descriptors.extend((0..dim).map(|c| d.data[c * cells + i] / n));
        let (cx, cy) = ((i % d.w) as f32, (i / d.w) as f32);
        k.xy.push([cx * 8.0 + 3.5, cy * 8.0 + 3.5]);
        let score = match &out.reliability {
            Some(r) if r.h == d.h && r.w == d.w => r.data.get(i).copied().unwrap_or(1.0),
            _ => 1.0,
        };
        k.scores.push(score);
    }
    k
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dense_sampling_takes_every_cell_at_its_centre() {
        // 2 x 3 cells, 2 channels: cell (x, y) holds (x + 1, y + 1) before normalisation
        let (h, w) = (2, 3);
        let mut data = vec![0.0; 2 * h * w];
        for y in 0..h {
            for x in 0..w {
                data[y * w + x] = (x + 1) as f32;
                data[h * w + y * w + x] = (y + 1) as f32;
            }
        }
        let out = NetOutputs { descriptors: Chw { c: 2, h, w, data }, logits: Chw::zeros(0, h, w), reliability: None };
        let k = dense(&out);
        assert_eq!((k.len(), k.dim), (6, 2));
        assert_eq!(k.xy[4], [11.5, 11.5]);
        // the descriptor at a cell centre is exactly the cell's, as `sample` reads it
        let mut v = [0.0f32; 2];
        sample(&out.descriptors, k.xy[5][0], k.xy[5][1], &mut v);
        assert_eq!(v, [3.0, 2.0]);
        let n = (9.0f32 + 4.0).sqrt();
        assert!((k.descriptors[10] - 3.0 / n).abs() < 1e-6 && (k.descriptors[11] - 2.0 / n).abs() < 1e-6);
        assert!(k.scores.iter().all(|&s| s == 1.0));
    }

    #[test]
    fn detect_keeps_local_maxima_of_the_heatmap_scored_by_reliability() {
        // 2 x 2 cells (16 x 16 pixels); logits favour the dustbin except three pixels
        let (h, w) = (2, 2);
        let mut logits = Chw::zeros(65, h, w);
        let cell = h * w;
        for i in 0..cell {
            logits.data[64 * cell + i] = 4.0;
        }
        // cell (0, 0): pixel (1, 1) strong, its neighbour (2, 1) a little weaker (suppressed)
        logits.data[9 * cell] = 8.0;
        logits.data[10 * cell] = 7.5;
        // cell (1, 1) (index 3): pixel (8 + 5, 8 + 6), weaker in the heatmap but reliable
        logits.data[(6 * 8 + 5) * cell + 3] = 7.0;
        let mut rel = Chw::zeros(1, h, w);
        rel.data = vec![0.2, 0.2, 0.2, 1.0];
        let mut desc = Chw::zeros(2, h, w);
        desc.data = vec![3.0, 3.0, 3.0, 0.0, 4.0, 4.0, 4.0, 1.0];
        let out = NetOutputs { descriptors: desc, logits, reliability: Some(rel) };
        let p = KeypointParams { nms_radius: 2, threshold: 0.05, max_keypoints: 10, border: 0 };
        let k = detect(&out, &p).unwrap();
        assert_eq!(k.xy, vec![[13.0, 14.0], [1.0, 1.0]], "the reliable one first; the neighbour suppressed");
        assert!(k.scores[0] > k.scores[1]);
        for d in k.descriptors.chunks(2) {
            assert!((d[0] * d[0] + d[1] * d[1] - 1.0).abs() < 1e-5);
        }
        assert_eq!(detect(&out, &KeypointParams { max_keypoints: 1, ..p }).unwrap().xy, vec![[13.0, 14.0]]);
        assert!(detect(&out, &KeypointParams { threshold: 0.99, ..p }).unwrap().is_empty());
    }
}
