//! The HOG baseline as VPR-Bench runs it (Zaffar et al., IJCV 2021, `vpr_techniques/HOG`):
//! the grey image resized to 512 x 512 (`cv2.resize`, bilinear), OpenCV's `HOGDescriptor`
//! with window 512, block 16, block stride 8, cell 16, 9 unsigned orientation bins, compared by
//! cosine similarity. Dalal & Triggs (CVPR 2005), in OpenCV's formulation (`modules/objdetect/src/
//! hog.cpp`): centred [-1, 0, 1] gradients (reflected borders), bilinear vote into the two nearest
//! orientation bins, a Gaussian window over each block (sigma = (block w + block h) / 8) times the
//! spatial weight of the cell interpolation, L2-Hys block normalisation (clip 0.2), blocks in
//! column-major order. Stored L2-normalised, so cosine similarity is a dot product.

use image::RgbImage;

/// VPR-Bench's HOG window (the image is resized to it).
pub const HOG_SIZE: usize = 512;
const BLOCK: usize = 16;
const STRIDE: usize = 8;
const BINS: usize = 9;
/// Blocks per side: (512 - 16) / 8 + 1.
const BLOCKS: usize = (HOG_SIZE - BLOCK) / STRIDE + 1;
/// Length of the descriptor: 63 x 63 blocks of one cell of 9 bins.
pub const HOG_DIM: usize = BLOCKS * BLOCKS * BINS;
/// L2-Hys clipping threshold (OpenCV's default).
const L2HYS_CLIP: f32 = 0.2;

/// Grey levels as OpenCV's RGB -> grey (ITU-R BT.601 luma), rounded to 8 bits.
fn grey(rgb: &RgbImage) -> Vec<u8> {
    rgb.pixels().map(|p| (0.299 * p.0[0] as f32 + 0.587 * p.0[1] as f32 + 0.114 * p.0[2] as f32).round().min(255.0) as u8).collect()
}

/// `cv2.resize(..., INTER_LINEAR)`: each output pixel samples the source at
/// ((x + 0.5) * scale - 0.5) bilinearly, coordinates clamped to the image.
pub fn resize_linear(src: &[u8], sw: usize, sh: usize, dw: usize, dh: usize) -> Vec<u8> {
    let taps = |d: usize, s: usize| -> Vec<(usize, usize, f32)> {
        let scale = s as f32 / d as f32;
        (0..d)
            .map(|x| {
                let f = ((x as f32 + 0.5) * scale - 0.5).max(0.0);
                let x0 = (f.floor() as usize).min(s - 1);
                let x1 = (x0 + 1).min(s - 1);
                (x0, x1, f - x0 as f32)
            })
            .collect()
    };
    let (tx, ty) = (taps(dw, sw), taps(dh, sh));
    let mut out = Vec::with_capacity(dw * dh);
    for &(y0, y1, fy) in &ty {
        let (r0, r1) = (&src[y0 * sw..(y0 + 1) * sw], &src[y1 * sw..(y1 + 1) * sw]);
        for &(x0, x1, fx) in &tx {
            let top = r0[x0] as f32 * (1.0 - fx) + r0[x1] as f32 * fx;
            let bottom = r1[x0] as f32 * (1.0 - fx) + r1[x1] as f32 * fx;
            out.push((top * (1.0 - fy) + bottom * fy).round() as u8);
        }
    }
    out
}

/// The VPR-Bench HOG descriptor of an image, L2-normalised (`HOG_DIM` values).
pub fn vprbench_hog(rgb: &RgbImage) -> Vec<f32> {
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    if w == 0 || h == 0 {
        return vec![0.0; HOG_DIM];
    }
    let img = resize_linear(&grey(rgb), w, h, HOG_SIZE, HOG_SIZE);
    hog_512(&img)
}

/// Per pixel of an n x n grey image: the two orientation bins and the magnitude split between them.
fn gradients(img: &[u8], n: usize) -> (Vec<[u8; 2]>, Vec<[f32; 2]>) {
    // reflect-101 border: index -1 reads 1, index n reads n - 2
    let at = |x: isize, y: isize| -> f32 {
        let r = |v: isize| if v < 0 { -v } else if v >= n as isize { 2 * n as isize - 2 - v } else { v } as usize;
        img[r(y) * n + r(x)] as f32
    };
    let mut bins = vec![[0u8; 2]; n * n];
    let mut mags = vec![[0f32; 2]; n * n];
    let scale = BINS as f32 / std::f32::consts::PI;
    for y in 0..n as isize {
        for x in 0..n as isize {
            let dx = at(x + 1, y) - at(x - 1, y);
            let dy = at(x, y + 1) - at(x, y - 1);
            let mag = (dx * dx + dy * dy).sqrt();
            let mut angle = dy.atan2(dx);
            if angle < 0.0 {
                angle += 2.0 * std::f32::consts::PI;
            }
            let a = angle * scale - 0.5;
            let lo = a.floor();
            let frac = a - lo;
            let wrap = |b: i32| b.rem_euclid(BINS as i32) as u8;
            let i = y as usize * n + x as usize;
            bins[i] = [wrap(lo as i32), wrap(lo as i32 + 1)];
            mags[i] = [mag * (1.0 - frac), mag * frac];
        }
    }
    (bins, mags)
}

/// Weight of block pixel (i, j): OpenCV's Gaussian window times the interpolation weight of the
/// block's single cell.
fn block_weights() -> [[f32; BLOCK]; BLOCK] {
    let sigma = (BLOCK + BLOCK) as f32 / 8.0;
    let scale = 1.0 / (2.0 * sigma * sigma);
    let cell = |k: usize| 1.0 - ((k as f32 + 0.5) / BLOCK as f32 - 0.5).abs();
    let mut w = [[0.0; BLOCK]; BLOCK];
    for (i, row) in w.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            let (di, dj) = (i as f32 - BLOCK as f32 * 0.5, j as f32 - BLOCK as f32 * 0.5);
            *v = (-(di * di + dj * dj) * scale).exp() * cell(i) * cell(j);
        }
    }
    w
}

/// HOG of a 512 x 512 grey image, L2-normalised.
fn hog_512(img: &[u8]) -> Vec<f32> {
    let (bins, mags) = gradients(img, HOG_SIZE);
    let weights = block_weights();
    let mut out = Vec::with_capacity(HOG_DIM);
    // blocks column-major: x outer, y inner (OpenCV's blockData order)
    for bx in 0..BLOCKS {
        for by in 0..BLOCKS {
            let mut hist = [0f32; BINS];
            for (i, wrow) in weights.iter().enumerate() {
                let row = (by * STRIDE + i) * HOG_SIZE + bx * STRIDE;
                for (j, &w) in wrow.iter().enumerate() {
                    let (b, m) = (bins[row + j], mags[row + j]);
                    hist[b[0] as usize] += m[0] * w;
                    hist[b[1] as usize] += m[1] * w;
                }
            }
            // L2-Hys
            let norm = hist.iter().map(|v| v * v).sum::<f32>().sqrt() + BINS as f32 * 0.1;
            hist.iter_mut().for_each(|v| *v = (*v / norm).min(L2HYS_CLIP));
            let norm = hist.iter().map(|v| v * v).sum::<f32>().sqrt() + 1e-3;
            out.extend(hist.iter().map(|v| v / norm));
        }
    }
    let n = out.iter().map(|v| v * v).sum::<f32>().sqrt();
    if n > 0.0 {
        out.iter_mut().for_each(|v| *v /= n);
    }
    out
}

/// The compact HOG's window: the grey image resized to this square ([`compact_hog`]).
pub const COMPACT_SIZE: usize = 64;
/// Its cells, in pixels of the window.
const COMPACT_CELL: usize = 8;
/// Cells per side of the window.
const COMPACT_CELLS: usize = COMPACT_SIZE / COMPACT_CELL;
/// Blocks per side: 2 x 2 cells, one cell apart.
const COMPACT_BLOCKS: usize = COMPACT_CELLS - 1;
/// Length of the compact HOG: 7 x 7 blocks of 2 x 2 cells of 9 bins.
pub const COMPACT_HOG_DIM: usize = COMPACT_BLOCKS * COMPACT_BLOCKS * 4 * BINS;

/// The compact HOG of an image (Dalal & Triggs, CVPR 2005, at thumbnail size): the grey image
/// resized to 64 x 64 (bilinear, as OpenCV), the same gradients and orientation votes as
/// [`vprbench_hog`], histograms of 8 x 8 cells, blocks of 2 x 2 cells one cell apart, each
/// L2-Hys normalised, then the whole L2-normalised (`COMPACT_HOG_DIM` values; cosine is a dot
/// product). What survives frames too small for keypoints: on a 64 x 32 copy of the Nordland dev
/// set it ranks as VPR-Bench's 512 x 512 HOG does (sweep 17), in 1,764 values instead of 35,721.
pub fn compact_hog(rgb: &RgbImage) -> Vec<f32> {
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    if w == 0 || h == 0 {
        return vec![0.0; COMPACT_HOG_DIM];
    }
    let img = resize_linear(&grey(rgb), w, h, COMPACT_SIZE, COMPACT_SIZE);
    let (bins, mags) = gradients(&img, COMPACT_SIZE);
    let mut cells = [[0f32; BINS]; COMPACT_CELLS * COMPACT_CELLS];
    for y in 0..COMPACT_SIZE {
        for x in 0..COMPACT_SIZE {
            let (b, m) = (bins[y * COMPACT_SIZE + x], mags[y * COMPACT_SIZE + x]);
            let cell = &mut cells[(y / COMPACT_CELL) * COMPACT_CELLS + x / COMPACT_CELL];
            cell[b[0] as usize] += m[0];
            cell[b[1] as usize] += m[1];
        }
    }
    let mut out = Vec::with_capacity(COMPACT_HOG_DIM);
    for by in 0..COMPACT_BLOCKS {
        for bx in 0..COMPACT_BLOCKS {
            let start = out.len();
            for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                out.extend_from_slice(&cells[(by + dy) * COMPACT_CELLS + bx + dx]);
            }
            // L2-Hys
            let block = &mut out[start..];
            let norm = (block.iter().map(|v| v * v).sum::<f32>() + 1e-6).sqrt();
            block.iter_mut().for_each(|v| *v = (*v / norm).min(L2HYS_CLIP));
            let norm = (block.iter().map(|v| v * v).sum::<f32>() + 1e-6).sqrt();
            block.iter_mut().for_each(|v| *v /= norm);
        }
    }
    let n = out.iter().map(|v| v * v).sum::<f32>().sqrt();
    if n > 0.0 {
        out.iter_mut().for_each(|v| *v /= n);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_resize_matches_opencv_sampling() {
        // 4 -> 2 samples at source x = 0.5 and 2.5: averages of pixel pairs
        assert_eq!(resize_linear(&[0, 100, 200, 250], 4, 1, 2, 1), vec![50, 225]);
        // 2 -> 4: x = -0.25 (clamped to 0), 0.25, 0.75, 1.25 (clamped to the last pixel)
        assert_eq!(resize_linear(&[0, 100], 2, 1, 4, 1), vec![0, 25, 75, 100]);
    }

    #[test]
    fn hog_is_unit_length_and_sees_orientation() {
        let stripes = |vertical: bool| {
            RgbImage::from_fn(64, 48, |x, y| {
                let v = if ((if vertical { x } else { y }) / 4) % 2 == 0 { 30 } else { 220 };
                image::Rgb([v, v, v])
            })
        };
        let (a, b) = (vprbench_hog(&stripes(true)), vprbench_hog(&stripes(false)));
        assert_eq!(a.len(), HOG_DIM);
        assert!((a.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-4);
        let cos = |p: &[f32], q: &[f32]| p.iter().zip(q).map(|(x, y)| x * y).sum::<f32>();
        assert!(cos(&a, &a) > 0.999 && cos(&a, &b) < 0.5, "{}", cos(&a, &b));
        // the compact HOG sees the same, at 64 x 32
        let small = |vertical: bool| {
            RgbImage::from_fn(64, 32, |x, y| {
                let v = if ((if vertical { x } else { y }) / 4) % 2 == 0 { 30 } else { 220 };
                image::Rgb([v, v, v])
            })
        };
        let (c, d) = (compact_hog(&small(true)), compact_hog(&small(false)));
        assert_eq!(c.len(), COMPACT_HOG_DIM);
        assert!((c.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-4);
        assert!(cos(&c, &d) < 0.5, "{}", cos(&c, &d));
        assert!(compact_hog(&RgbImage::new(0, 0)).iter().all(|&v| v == 0.0));
        // a flat image has no gradients: all zeros, not NaN
        assert!(compact_hog(&RgbImage::from_pixel(64, 32, image::Rgb([90, 90, 90]))).iter().all(|&v| v == 0.0));
    }
}
