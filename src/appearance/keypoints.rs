//! SuperPoint-style keypoint decoding of a network's cell outputs (DeTone, Malisiewicz &
//! Rabinovich, "SuperPoint", CVPRW 2018; the same layout as XFeat's keypoint head): per 8x8 cell a
//! softmax over 65 logits, the "no keypoint" dustbin dropped, the 64 probabilities shuffled to
//! full resolution; the score is that probability times the reliability map (when the network
//! has one); then non-maximum suppression, a threshold, the best N, and descriptors sampled
//! bilinearly from the dense map and L2-normalised.

use super::nn::Chw;
use super::NetOutputs;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeypointParams {
    /// Keep a pixel only if no pixel within this Chebyshev radius scores higher.
    pub nms_radius: usize,
    pub threshold: f32,
    pub max_keypoints: usize,
    /// Ignore keypoints this close to the image border (pixels).
    pub border: usize,
}

/// Keypoints of one image, in the coordinates of the network input.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Keypoints {
    pub xy: Vec<[f32; 2]>,
    pub scores: Vec<f32>,
    /// `dim` values per keypoint, unit length.
    pub descriptors: Vec<f32>,
    pub dim: usize,
}

impl Keypoints {
    pub fn len(&self) -> usize {
        self.xy.len()
    }
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

/// Full-resolution score map (H x W = 8h x 8w) from the cell logits and reliability; fails
/// when the outputs are not SuperPoint's layout.
pub fn score_map(out: &NetOutputs) -> Result<(Vec<f32>, usize, usize), String> {
    let l = &out.logits;
    let rel_ok = out.reliability.as_ref().is_none_or(|r| r.c == 1 && r.h > 0 && r.w > 0 && r.is_consistent());
    if l.c != 65 || !l.is_consistent() || !rel_ok {
        return Err(format!("keypoint logits are {}x{}x{} (need 65 channels) or the reliability map is not one channel", l.c, l.h, l.w));
    }
    let (h, w) = (l.h, l.w);
    let (hh, ww) = (h * 8, w * 8);
    let mut scores = vec![0.0f32; hh * ww];
    let cell = h * w;
    for cy in 0..h {
        for cx in 0..w {
            let i = cy * w + cx;
            let m = (0..65).map(|c| l.data[c * cell + i]).fold(f32::NEG_INFINITY, f32::max);
            let sum: f32 = (0..65).map(|c| (l.data[c * cell + i] - m).exp()).sum();
            for k in 0..64 {
                let (ky, kx) = (k / 8, k % 8);
                scores[(cy * 8 + ky) * ww + cx * 8 + kx] = (l.data[k * cell + i] - m).exp() / sum;
            }
        }
    }
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
pub fn extract(out: &NetOutputs, p: &KeypointParams) -> Result<Keypoints, String> {
    let d = &out.descriptors;
    if d.c == 0 || d.h == 0 || d.w == 0 || !d.is_consistent() {
        return Err(format!("descriptor map is {}x{}x{}", d.c, d.h, d.w));
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
}
