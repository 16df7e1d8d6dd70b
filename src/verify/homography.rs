//! Plane-to-plane homographies from point correspondences: the minimal 4-point solution and the
//! least-squares refit on many points, both as the direct linear transform (DLT) with h33 = 1 on
//! Hartley-normalised points (Hartley & Zisserman, "Multiple View Geometry", 2nd ed., §4.1 and
//! §4.4), solved by Gaussian elimination with partial pivoting; and the forward transfer error
//! that decides inliers.

/// A 3x3 homography, row-major, mapping query points to reference points.
pub type Homography = [f64; 9];

/// Applies `h` to (x, y); `None` when the point maps to infinity or behind the camera (w <= 0,
/// which no view of a real plane produces for points seen in both images).
#[inline]
pub fn apply(h: &Homography, p: [f64; 2]) -> Option<[f64; 2]> {
    let w = h[6] * p[0] + h[7] * p[1] + h[8];
    if w <= 1e-12 {
        return None;
    }
    Some([(h[0] * p[0] + h[1] * p[1] + h[2]) / w, (h[3] * p[0] + h[4] * p[1] + h[5]) / w])
}

/// Squared distance between `h(p)` and `q`; infinite when `h(p)` is not finite.
#[inline]
pub fn transfer_error2(h: &Homography, p: [f64; 2], q: [f64; 2]) -> f64 {
    match apply(h, p) {
        Some(m) => (m[0] - q[0]).powi(2) + (m[1] - q[1]).powi(2),
        None => f64::INFINITY,
    }
}

/// Similarity that moves the points' centroid to the origin and their mean distance to it to
/// sqrt(2) (Hartley normalisation), as (scale, tx, ty): x' = scale * x + tx.
fn normaliser(points: impl Iterator<Item = [f64; 2]> + Clone) -> Option<(f64, f64, f64)> {
    let n = points.clone().count() as f64;
    if n == 0.0 {
        return None;
    }
    let (cx, cy) = points.clone().fold((0.0, 0.0), |(a, b), p| (a + p[0], b + p[1]));
    let (cx, cy) = (cx / n, cy / n);
    let mean = points.map(|p| ((p[0] - cx).powi(2) + (p[1] - cy).powi(2)).sqrt()).sum::<f64>() / n;
    if !(mean > 1e-12) {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean;
    Some((s, -s * cx, -s * cy))
}

/// Solves the n x n system `a x = b` (a row-major, destroyed) by Gaussian elimination with partial
/// pivoting; `None` when it is singular or ill-conditioned.
fn solve<const N: usize>(a: &mut [[f64; N]; N], b: &mut [f64; N]) -> Option<[f64; N]> {
    let scale = a.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    if !(scale > 0.0) {
        return None;
    }
    for c in 0..N {
        let p = (c..N).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        if a[p][c].abs() <= 1e-12 * scale {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        for r in c + 1..N {
            let f = a[r][c] / a[c][c];
            if f != 0.0 {
                for k in c..N {
                    a[r][k] -= f * a[c][k];
                }
                b[r] -= f * b[c];
            }
        }
    }
    let mut x = [0.0; N];
    for r in (0..N).rev() {
        let s: f64 = (r + 1..N).map(|k| a[r][k] * x[k]).sum();
        x[r] = (b[r] - s) / a[r][r];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// The two DLT rows of correspondence (x, y) -> (u, v) with h33 = 1, added to the normal
/// equations `ata`, `atb` (least squares over all correspondences given).
fn accumulate(ata: &mut [[f64; 8]; 8], atb: &mut [f64; 8], p: [f64; 2], q: [f64; 2]) {
    let (x, y, u, v) = (p[0], p[1], q[0], q[1]);
    let rows = [([x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y], u), ([0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y], v)];
    for (row, rhs) in rows {
        for i in 0..8 {
            if row[i] == 0.0 {
                continue;
            }
            for j in 0..8 {
                ata[i][j] += row[i] * row[j];
            }
            atb[i] += row[i] * rhs;
        }
    }
}

/// The homography taking `src[i]` to `dst[i]` that minimises the algebraic error over all pairs
/// (exact for 4 pairs in general position); `None` for fewer than 4 pairs or a degenerate set.
pub fn fit(src: &[[f64; 2]], dst: &[[f64; 2]]) -> Option<Homography> {
    if src.len() < 4 || src.len() != dst.len() {
        return None;
    }
    let (s1, tx1, ty1) = normaliser(src.iter().copied())?;
    let (s2, tx2, ty2) = normaliser(dst.iter().copied())?;
    let mut ata = [[0.0; 8]; 8];
    let mut atb = [0.0; 8];
    for (p, q) in src.iter().zip(dst) {
        accumulate(&mut ata, &mut atb, [s1 * p[0] + tx1, s1 * p[1] + ty1], [s2 * q[0] + tx2, s2 * q[1] + ty2]);
    }
    let h = solve(&mut ata, &mut atb)?;
    let hn = [h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0];
    // undo the normalisations: H = T2^-1 Hn T1
    let t1 = [s1, 0.0, tx1, 0.0, s1, ty1, 0.0, 0.0, 1.0];
    let t2_inv = [1.0 / s2, 0.0, -tx2 / s2, 0.0, 1.0 / s2, -ty2 / s2, 0.0, 0.0, 1.0];
    let h = mul(&t2_inv, &mul(&hn, &t1));
    let n = h[8];
    (n.abs() > 1e-12 && h.iter().all(|v| v.is_finite())).then(|| h.map(|v| v / n))
}

/// 3x3 matrix product.
fn mul(a: &[f64; 9], b: &[f64; 9]) -> [f64; 9] {
    let mut c = [0.0; 9];
    for r in 0..3 {
        for k in 0..3 {
            c[r * 3 + k] = (0..3).map(|j| a[r * 3 + j] * b[j * 3 + k]).sum();
        }
    }
    c
}

/// Twice the signed area of triangle (a, b, c).
#[inline]
pub fn cross(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> f64 {
    (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
}

/// Whether a 4-point sample can define a homography of a real plane: no three points nearly
/// collinear in either image (triangle area above `min_area`, squared coordinate units), and the
/// orientation of every triple the same in both images (a view of a plane does not mirror it).
pub fn sample_is_valid(src: &[[f64; 2]; 4], dst: &[[f64; 2]; 4], min_area: f64) -> bool {
    const TRIPLES: [[usize; 3]; 4] = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]];
    TRIPLES.iter().all(|&[a, b, c]| {
        let (s, d) = (cross(src[a], src[b], src[c]), cross(dst[a], dst[b], dst[c]));
        s.abs() > min_area && d.abs() > min_area && (s > 0.0) == (d > 0.0)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn four_points_give_the_homography_that_made_them() {
        let h: Homography = [1.1, 0.05, 0.02, -0.03, 0.95, 0.01, 0.2, -0.1, 1.0];
        let src = [[0.1, 0.1], [0.8, 0.15], [0.7, 0.6], [0.2, 0.55]];
        let dst = src.map(|p| apply(&h, p).unwrap());
        let g = fit(&src, &dst).unwrap();
        for (a, b) in g.iter().zip(&h) {
            assert!((a - b).abs() < 1e-9, "{g:?} vs {h:?}");
        }
        // more points: the same homography by least squares
        let more: Vec<[f64; 2]> = (0..20).map(|i| [0.05 * i as f64, 0.3 + 0.02 * (i * i % 7) as f64]).collect();
        let to: Vec<[f64; 2]> = more.iter().map(|&p| apply(&h, p).unwrap()).collect();
        let g = fit(&more, &to).unwrap();
        assert!(more.iter().zip(&to).all(|(&p, &q)| transfer_error2(&g, p, q) < 1e-18));
    }

    #[test]
    fn collinear_or_mirrored_samples_are_refused() {
        let src = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        assert!(sample_is_valid(&src, &src, 1e-6));
        let line = [[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [0.0, 1.0]];
        assert!(!sample_is_valid(&line, &src, 1e-6));
        let mirrored = src.map(|p| [-p[0], p[1]]);
        assert!(!sample_is_valid(&src, &mirrored, 1e-6));
        let all_on_a_line = [[0.0, 0.0], [0.25, 0.0], [0.5, 0.0], [1.0, 0.0]];
        assert!(fit(&all_on_a_line, &src).is_none());
    }
}
