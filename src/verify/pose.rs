//! Relative pose (beyond the paper; issue 48 part 6): with the camera's intrinsics, the keypoint
//! matches of a verified pair give the rotation and the direction of translation between the two
//! views, what a SLAM back end adds to its pose graph for a loop closure.
//!
//! The matches' positions are normalised with the intrinsics K ([`Camera`]); an essential matrix
//! is estimated in a RANSAC (adaptive stopping for samples of 5) whose minimal solver is the
//! five-point method of Stewénius, Engels & Nistér ("Recent developments on direct relative
//! orientation", ISPRS 2006: the 4-dimensional null space of the 5 epipolar constraints, the ten
//! cubic constraints on an essential matrix, and the action matrix of multiplication by x over
//! the 10 monomials of degree <= 2, whose real eigenvectors are the solutions), inliers decided
//! by the Sampson distance. Each new best model is refitted on its inliers by the normalised
//! eight-point method projected onto the essential manifold (LO-RANSAC), and the final one by
//! Levenberg-Marquardt over (R, t) on the inliers' Sampson distances. R and t come from the
//! SVD of E (Hartley & Zisserman §9.6.2), of the four candidates the one that puts the most
//! inliers in front of both cameras.
//!
//! The convention: a point X in the query camera's frame is R X + s t in the reference camera's
//! (s > 0 unknown: the scale is not observable from two views), t of length 1. Where the matches
//! are explained by a rotation alone (no parallax: a camera that turned on the spot, or a scene
//! far away against the baseline) the translation is not observable and the estimate is refused
//! ([`PoseError::NoParallax`]) rather than a direction made up; where one plane holds them (a
//! homography explains them) two poses fit alike and it is refused too ([`PoseError::Planar`]).

use super::ransac::{iterations_for, sample, RansacParams};
use crate::descriptors::keypoints::KeypointsRef;
use crate::error::{Error, Result};
use crate::util::SplitMix64;
use nalgebra::{Matrix3, SMatrix, Vector3};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Pinhole intrinsics of the images a camera takes, in pixels of images of `width` x `height`
/// (frames of another resolution with the same aspect ratio are scaled to it).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point, x (pixels from the left edge).
    pub cx: f64,
    /// Principal point, y (pixels from the top edge).
    pub cy: f64,
    /// Width of the images the intrinsics are for, pixels.
    pub width: u32,
    /// Height of the images the intrinsics are for, pixels.
    pub height: u32,
}

impl Camera {
    /// Reads a camera file: TOML (`.toml`) or JSON (any other name) with `fx`, `fy`, `cx`, `cy`,
    /// `width`, `height`. A missing file, a malformed one or implausible values are errors naming
    /// the file and the problem.
    pub fn load(path: &Path) -> Result<Camera> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let what = || format!("camera file {}", path.display());
        let cam: Camera = match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
            Some("toml") => toml::from_str(&text).map_err(|e| Error::invalid(what(), e.to_string()))?,
            _ => serde_json::from_str(&text).map_err(|e| Error::invalid(what(), e.to_string()))?,
        };
        cam.check().map_err(|r| Error::invalid(what(), r))?;
        Ok(cam)
    }

    /// What is wrong with the intrinsics, if anything: focal lengths positive and finite, the
    /// principal point inside the image, a non-empty image.
    pub fn check(&self) -> std::result::Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!("width x height is {} x {}: the image size must not be 0", self.width, self.height));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} = {v}: a focal length must be a positive number of pixels"));
            }
        }
        for (name, v, side) in [("cx", self.cx, self.width), ("cy", self.cy, self.height)] {
            if !(v.is_finite() && v >= 0.0 && v <= side as f64) {
                return Err(format!("{name} = {v}: the principal point must lie inside the {} x {} image", self.width, self.height));
            }
        }
        Ok(())
    }

    /// Whether an image of `width` x `height` has the camera's aspect ratio (within a pixel of
    /// rounding at the camera's size): the intrinsics scale to it.
    pub fn fits(&self, width: u32, height: u32) -> bool {
        let scaled = height as f64 * self.width as f64 / width.max(1) as f64;
        (scaled - self.height as f64).abs() <= 1.0 + self.height as f64 * 2e-3
    }

    /// The normalised image coordinates (K^-1 applied) of a keypoint position given in fractions
    /// of the image's long side (the verification keypoints' units) of an image with the
    /// camera's aspect ratio.
    pub fn normalise(&self, p: [f64; 2]) -> [f64; 2] {
        let long = self.width.max(self.height) as f64;
        [(p[0] * long - self.cx) / self.fx, (p[1] * long - self.cy) / self.fy]
    }

    /// The mean focal length, pixels.
    fn focal(&self) -> f64 {
        0.5 * (self.fx + self.fy)
    }
}

/// The relative pose of a verified pair: a point X in the query camera's frame is
/// `rotation` X + s `translation_unit` in the reference camera's, s > 0 unknown.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RelativePose {
    /// The rotation, row-major 3 x 3.
    pub rotation: [[f64; 3]; 3],
    /// The same rotation as a unit quaternion (x, y, z, w), w >= 0.
    pub quaternion: [f64; 4],
    /// The direction of translation (length 1).
    pub translation_unit: [f64; 3],
    /// The rotation's angle, degrees.
    pub rotation_deg: f64,
    /// Matches the pose explains (Sampson distance within the threshold, in front of both cameras).
    pub inliers: u32,
    /// Matches the pose was estimated from.
    pub matches: u32,
}

/// Why no relative pose was estimated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PoseError {
    /// Fewer matches than the estimate needs.
    #[error("{have} matches, the relative pose needs at least {need}")]
    TooFewMatches {
        /// Matches given.
        have: usize,
        /// Matches needed.
        need: usize,
    },
    /// No essential matrix explains enough of the matches.
    #[error("no essential matrix explains at least {need} of the {matches} matches")]
    NoModel {
        /// Matches given.
        matches: usize,
        /// Inliers needed.
        need: usize,
    },
    /// The matches are explained by a rotation alone (no parallax): the translation is not
    /// observable.
    #[error("{rotation_inliers} of the {inliers} inliers are explained by a rotation alone: no parallax, the translation is not observable")]
    NoParallax {
        /// Inliers of the essential matrix.
        inliers: usize,
        /// Of them, those a rotation alone explains.
        rotation_inliers: usize,
    },
    /// The matches lie on one plane (a homography explains them): two poses explain them alike.
    #[error("{plane_inliers} of the {inliers} inliers lie on one plane: two poses explain them alike")]
    Planar {
        /// Inliers of the essential matrix.
        inliers: usize,
        /// Of them, those one homography explains.
        plane_inliers: usize,
    },
}

/// Parameters of the estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseParams {
    /// A match is an inlier when its Sampson distance is below this, in normalised image
    /// coordinates (pixels / focal length).
    pub threshold: f64,
    /// Most RANSAC iterations.
    pub max_iterations: u32,
    /// Stop once a better model would have been found with this probability.
    pub confidence: f64,
    /// Seed of the sampling.
    pub seed: u64,
    /// Fewest inliers of an accepted pose.
    pub min_inliers: usize,
}

/// The Sampson threshold of [`PoseParams::for_camera`], fractions of the image's long side (2 px
/// at a long side of 640: the keypoints' positions are stored to the working image's pixel).
pub const THRESHOLD_OF_LONG_SIDE: f64 = 0.003;
/// Fewest inliers of an accepted pose (of [`PoseParams::for_camera`]).
pub const MIN_INLIERS: usize = 12;
/// Share of the inliers a rotation alone may explain before the pose is refused as without
/// parallax: where most are (a car waiting at a light), the translation rests on the few that
/// moved, mostly other traffic. On CamVid's drive a rotation explains 5-23 % of the inliers of a
/// moving car's consecutive frames (1 s apart) and 82-93 % of those of a stopped car's
/// (`tests/pose.rs`); 0.9 let the 82 % pair through with a translation straight down the image.
const NO_PARALLAX_SHARE: f64 = 0.5;
/// Share of the inliers one homography may explain before the pose is refused as planar.
const PLANAR_SHARE: f64 = 0.9;
/// Least-squares refits of a new best model (each kept only if it gathers more inliers).
const REFINE_ROUNDS: usize = 3;
/// Levenberg-Marquardt steps of the final refinement.
const LM_STEPS: usize = 20;

impl PoseParams {
    /// The parameters for matches of `camera`'s images: the threshold
    /// [`THRESHOLD_OF_LONG_SIDE`] in normalised coordinates, 1,000 iterations at most, confidence
    /// 0.999.
    pub fn for_camera(camera: &Camera, seed: u64) -> PoseParams {
        let long = camera.width.max(camera.height) as f64;
        PoseParams {
            threshold: THRESHOLD_OF_LONG_SIDE * long / camera.focal(),
            max_iterations: 1000,
            confidence: 0.999,
            seed,
            min_inliers: MIN_INLIERS,
        }
    }
}

/// The relative pose of a pair from its keypoint matches (query keypoint, reference keypoint):
/// positions normalised with `camera`, then [`estimate`].
pub fn pair_pose(
    camera: &Camera,
    q: KeypointsRef,
    r: KeypointsRef,
    matches: &[(u32, u32)],
    p: &PoseParams,
) -> std::result::Result<RelativePose, PoseError> {
    let (a, b): (Vec<[f64; 2]>, Vec<[f64; 2]>) = matches
        .iter()
        .filter(|&&(i, j)| (i as usize) < q.len() && (j as usize) < r.len())
        .map(|&(i, j)| (camera.normalise(q.position(i as usize)), camera.normalise(r.position(j as usize))))
        .unzip();
    estimate(&a, &b, p)
}

type M3 = Matrix3<f64>;
type V3 = Vector3<f64>;

/// The relative pose from correspondences in normalised image coordinates (`query[i]` seen at
/// `reference[i]`).
pub fn estimate(query: &[[f64; 2]], reference: &[[f64; 2]], p: &PoseParams) -> std::result::Result<RelativePose, PoseError> {
    let n = query.len().min(reference.len());
    let need = p.min_inliers.max(8);
    if n < need {
        return Err(PoseError::TooFewMatches { have: n, need });
    }
    let a: Vec<V3> = query[..n].iter().map(|v| V3::new(v[0], v[1], 1.0)).collect();
    let b: Vec<V3> = reference[..n].iter().map(|v| V3::new(v[0], v[1], 1.0)).collect();
    if a.iter().chain(&b).any(|v| !v.iter().all(|x| x.is_finite())) {
        return Err(PoseError::NoModel { matches: n, need });
    }
    let t2 = p.threshold * p.threshold;
    let count = |e: &M3| (0..n).filter(|&i| sampson2(e, &a[i], &b[i]) < t2).count();
    let inliers_of = |e: &M3| -> Vec<usize> { (0..n).filter(|&i| sampson2(e, &a[i], &b[i]) < t2).collect() };
    let mut rng = SplitMix64::new(p.seed);
    let mut best: Option<(M3, usize)> = None;
    let mut bound = p.max_iterations as f64;
    let mut it = 0u32;
    while (it as f64) < bound.min(p.max_iterations as f64) {
        it += 1;
        let idx = sample::<5>(&mut rng, n);
        for e in five_point(&idx.map(|i| a[i]), &idx.map(|i| b[i])) {
            let c = count(&e);
            if best.is_some_and(|(_, bc)| c <= bc) {
                continue;
            }
            let (mut e, mut c) = (e, c);
            for _ in 0..REFINE_ROUNDS {
                let inl = inliers_of(&e);
                match eight_point(&inl.iter().map(|&i| a[i]).collect::<Vec<_>>(), &inl.iter().map(|&i| b[i]).collect::<Vec<_>>()) {
                    Some(g) if count(&g) > c => {
                        c = count(&g);
                        e = g;
                    }
                    _ => break,
                }
            }
            best = Some((e, c));
            bound = iterations_for(c as f64 / n as f64, p.confidence, 5);
        }
    }
    let Some((e, _)) = best.filter(|&(_, c)| c >= need) else {
        return Err(PoseError::NoModel { matches: n, need });
    };
    let inl = inliers_of(&e);
    let (ia, ib): (Vec<V3>, Vec<V3>) = inl.iter().map(|&i| (a[i], b[i])).unzip();
    // a rotation alone that explains the inliers: no parallax, the translation is unobservable
    // (the residuals of a rotation or a homography are point distances, the Sampson distance a
    // distance to a line: twice the threshold)
    let rotation_inliers = rotation_only_inliers(&ia, &ib, 2.0 * p.threshold, p.seed);
    if rotation_inliers as f64 >= NO_PARALLAX_SHARE * inl.len() as f64 {
        return Err(PoseError::NoParallax { inliers: inl.len(), rotation_inliers });
    }
    // the inliers on one plane: two essential matrices explain them, the pose is ambiguous
    let plane = |v: &V3| [v[0], v[1]];
    let homography = RansacParams { threshold: 2.0 * p.threshold, max_iterations: 500, confidence: 0.999, seed: p.seed, refine: true };
    let plane_inliers =
        super::ransac::ransac_homography(&ia.iter().map(plane).collect::<Vec<_>>(), &ib.iter().map(plane).collect::<Vec<_>>(), &homography)
            .map_or(0, |(_, f)| f.iter().filter(|&&b| b).count());
    if plane_inliers as f64 >= PLANAR_SHARE * inl.len() as f64 {
        return Err(PoseError::Planar { inliers: inl.len(), plane_inliers });
    }
    let (r, t) = decompose(&e, &ia, &ib).ok_or(PoseError::NoModel { matches: n, need })?;
    let (r, t) = refine(r, t, &ia, &ib);
    // the final inliers: within the threshold and in front of both cameras
    let e = skew(&t) * r;
    let inliers = (0..n).filter(|&i| sampson2(&e, &a[i], &b[i]) < t2 && in_front(&r, &t, &a[i], &b[i])).count();
    if inliers < need {
        return Err(PoseError::NoModel { matches: n, need });
    }
    Ok(pose_of(&r, &t, inliers, n))
}

/// The reported form of (R, t).
fn pose_of(r: &M3, t: &V3, inliers: usize, matches: usize) -> RelativePose {
    let q = nalgebra::UnitQuaternion::from_matrix(r);
    let q = if q.w < 0.0 { nalgebra::UnitQuaternion::new_unchecked(-q.into_inner()) } else { q };
    RelativePose {
        rotation: [[r[(0, 0)], r[(0, 1)], r[(0, 2)]], [r[(1, 0)], r[(1, 1)], r[(1, 2)]], [r[(2, 0)], r[(2, 1)], r[(2, 2)]]],
        quaternion: [q.i, q.j, q.k, q.w],
        translation_unit: [t[0], t[1], t[2]],
        rotation_deg: q.angle().to_degrees(),
        inliers: inliers as u32,
        matches: matches as u32,
    }
}

/// Squared Sampson distance of (a, b) to the epipolar geometry b^T E a = 0.
fn sampson2(e: &M3, a: &V3, b: &V3) -> f64 {
    let ea = e * a;
    let etb = e.transpose() * b;
    let v = b.dot(&ea);
    let d = ea[0] * ea[0] + ea[1] * ea[1] + etb[0] * etb[0] + etb[1] * etb[1];
    if d > 1e-300 {
        v * v / d
    } else {
        f64::INFINITY
    }
}

/// [t]x, the matrix of the cross product with t.
fn skew(t: &V3) -> M3 {
    M3::new(0.0, -t[2], t[1], t[2], 0.0, -t[0], -t[1], t[0], 0.0)
}

/// A polynomial of degree <= 3 in (x, y, z): coefficients by monomial, in [`MONOMIALS`] order.
type Poly = [f64; 20];

/// Exponents (x, y, z) of the monomials of degree <= 3: the 10 cubics (eliminated), then the 10
/// of degree <= 2 (the basis of the quotient ring the action matrix works in; `x` at 16, `y` 17,
/// `z` 18, `1` 19).
const MONOMIALS: [[u8; 3]; 20] = [
    [3, 0, 0],
    [0, 3, 0],
    [0, 0, 3],
    [2, 1, 0],
    [2, 0, 1],
    [1, 2, 0],
    [0, 2, 1],
    [1, 0, 2],
    [0, 1, 2],
    [1, 1, 1],
    [2, 0, 0],
    [1, 1, 0],
    [1, 0, 1],
    [0, 2, 0],
    [0, 1, 1],
    [0, 0, 2],
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [0, 0, 0],
];

/// Index of the monomial of exponents `e` in [`MONOMIALS`].
fn mono(e: [u8; 3]) -> usize {
    MONOMIALS.iter().position(|m| *m == e).expect("a monomial of degree <= 3")
}

/// Product of two polynomials whose degrees sum to at most 3.
fn pmul(a: &Poly, b: &Poly) -> Poly {
    let mut out = [0.0; 20];
    for (i, &ca) in a.iter().enumerate() {
        if ca == 0.0 {
            continue;
        }
        for (j, &cb) in b.iter().enumerate() {
            if cb == 0.0 {
                continue;
            }
            let (ma, mb) = (MONOMIALS[i], MONOMIALS[j]);
            out[mono([ma[0] + mb[0], ma[1] + mb[1], ma[2] + mb[2]])] += ca * cb;
        }
    }
    out
}

fn padd(a: &Poly, b: &Poly) -> Poly {
    std::array::from_fn(|i| a[i] + b[i])
}

fn pscale(a: &Poly, s: f64) -> Poly {
    a.map(|v| v * s)
}

/// The essential matrices through 5 correspondences (b^T E a = 0), up to 10.
fn five_point(a: &[V3; 5], b: &[V3; 5]) -> Vec<M3> {
    // the 5 epipolar constraints on E's 9 entries (row-major), padded to a square for a full SVD
    let mut q = SMatrix::<f64, 9, 9>::zeros();
    for i in 0..5 {
        for r in 0..3 {
            for c in 0..3 {
                q[(i, 3 * r + c)] = b[i][r] * a[i][c];
            }
        }
    }
    let svd = q.svd(false, true);
    let Some(vt) = svd.v_t else { return vec![] };
    let mut order: Vec<usize> = (0..9).collect();
    order.sort_by(|&i, &j| svd.singular_values[j].total_cmp(&svd.singular_values[i]));
    // the null space: the right singular vectors of the 4 smallest singular values
    let basis: [[f64; 9]; 4] = std::array::from_fn(|k| std::array::from_fn(|c| vt[(order[5 + k], c)]));
    // E = x X + y Y + z Z + W, each entry a polynomial of degree 1
    let e: [[Poly; 3]; 3] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            let mut p = [0.0; 20];
            p[16] = basis[0][3 * r + c];
            p[17] = basis[1][3 * r + c];
            p[18] = basis[2][3 * r + c];
            p[19] = basis[3][3 * r + c];
            p
        })
    });
    // the ten cubic constraints: det(E) = 0 and 2 E E^T E - tr(E E^T) E = 0
    let mut eqs: Vec<Poly> = Vec::with_capacity(10);
    let det = {
        let m = |r1: usize, c1: usize, r2: usize, c2: usize| padd(&pmul(&e[r1][c1], &e[r2][c2]), &pscale(&pmul(&e[r1][c2], &e[r2][c1]), -1.0));
        let t0 = pmul(&e[0][0], &m(1, 1, 2, 2));
        let t1 = pmul(&e[0][1], &m(1, 0, 2, 2));
        let t2 = pmul(&e[0][2], &m(1, 0, 2, 1));
        padd(&padd(&t0, &pscale(&t1, -1.0)), &t2)
    };
    eqs.push(det);
    let eet: [[Poly; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| (0..3).fold([0.0; 20], |acc, k| padd(&acc, &pmul(&e[r][k], &e[c][k])))));
    let trace = padd(&padd(&eet[0][0], &eet[1][1]), &eet[2][2]);
    for r in 0..3 {
        for c in 0..3 {
            let eete = (0..3).fold([0.0; 20], |acc, k| padd(&acc, &pmul(&eet[r][k], &e[k][c])));
            eqs.push(padd(&pscale(&eete, 2.0), &pscale(&pmul(&trace, &e[r][c]), -1.0)));
        }
    }
    // Gauss-Jordan on the cubics: each cubic monomial as a combination of the basis
    let cubic = SMatrix::<f64, 10, 10>::from_fn(|i, j| eqs[i][j]);
    let rest = SMatrix::<f64, 10, 10>::from_fn(|i, j| eqs[i][10 + j]);
    let Some(g) = cubic.lu().solve(&rest) else { return vec![] };
    // the action matrix of multiplication by x on the basis (x^2, xy, xz, y^2, yz, z^2, x, y, z, 1)
    let row_of = |m: [u8; 3]| -> [f64; 10] {
        let k = mono(m);
        match k < 10 {
            true => std::array::from_fn(|j| -g[(k, j)]),
            false => std::array::from_fn(|j| if j == k - 10 { 1.0 } else { 0.0 }),
        }
    };
    let mut act = SMatrix::<f64, 10, 10>::zeros();
    for (i, m) in MONOMIALS[10..].iter().enumerate() {
        let row = row_of([m[0] + 1, m[1], m[2]]);
        for j in 0..10 {
            act[(i, j)] = row[j];
        }
    }
    if !act.iter().all(|v| v.is_finite()) {
        return vec![];
    }
    let Some(eigen) = act.try_schur(1e-12, 200) else { return vec![] };
    let mut out = Vec::new();
    for lambda in eigen.complex_eigenvalues().iter() {
        if lambda.im.abs() > 1e-8 * (1.0 + lambda.re.abs()) {
            continue;
        }
        // the eigenvector: the null vector of act - lambda I
        let m = act - SMatrix::<f64, 10, 10>::identity() * lambda.re;
        let s = m.svd(false, true);
        let Some(vt) = s.v_t else { continue };
        let k = (0..10).min_by(|&i, &j| s.singular_values[i].total_cmp(&s.singular_values[j])).unwrap_or(9);
        let v: [f64; 10] = std::array::from_fn(|c| vt[(k, c)]);
        if v[9].abs() < 1e-12 {
            continue;
        }
        let (x, y, z) = (v[6] / v[9], v[7] / v[9], v[8] / v[9]);
        let e = M3::from_fn(|r, c| x * basis[0][3 * r + c] + y * basis[1][3 * r + c] + z * basis[2][3 * r + c] + basis[3][3 * r + c]);
        let norm = e.norm();
        if norm.is_finite() && norm > 1e-12 {
            out.push(e / norm);
        }
    }
    out
}

/// The essential matrix of many correspondences by the normalised eight-point method (Hartley
/// normalisation, least squares, then the closest essential matrix: singular values (1, 1, 0)).
fn eight_point(a: &[V3], b: &[V3]) -> Option<M3> {
    if a.len() < 8 {
        return None;
    }
    let (ta, tb) = (hartley(a)?, hartley(b)?);
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for (pa, pb) in a.iter().zip(b) {
        let (u, v) = (ta * pa, tb * pb);
        let row = SMatrix::<f64, 1, 9>::from_fn(|_, k| v[k / 3] * u[k % 3]);
        ata += row.transpose() * row;
    }
    let eig = ata.symmetric_eigen();
    let k = (0..9).min_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]))?;
    let f = M3::from_fn(|r, c| eig.eigenvectors[(3 * r + c, k)]);
    let e = tb.transpose() * f * ta;
    closest_essential(&e)
}

/// The similarity moving points' centroid to the origin and their mean distance to sqrt(2).
fn hartley(p: &[V3]) -> Option<M3> {
    let n = p.len() as f64;
    let (cx, cy) = p.iter().fold((0.0, 0.0), |(x, y), v| (x + v[0], y + v[1]));
    let (cx, cy) = (cx / n, cy / n);
    let mean = p.iter().map(|v| ((v[0] - cx).powi(2) + (v[1] - cy).powi(2)).sqrt()).sum::<f64>() / n;
    if !(mean > 1e-12) {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean;
    Some(M3::new(s, 0.0, -s * cx, 0.0, s, -s * cy, 0.0, 0.0, 1.0))
}

/// The essential matrix nearest `e` (Frobenius): its singular values made (1, 1, 0).
fn closest_essential(e: &M3) -> Option<M3> {
    let svd = e.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| svd.singular_values[j].total_cmp(&svd.singular_values[i]));
    let d = M3::from_fn(|r, c| if r == c && (r == order[0] || r == order[1]) { 1.0 } else { 0.0 });
    let out = u * d * vt;
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// The four (R, t) of an essential matrix; of them the one that puts the most correspondences in
/// front of both cameras.
fn decompose(e: &M3, a: &[V3], b: &[V3]) -> Option<(M3, V3)> {
    let svd = e.svd(true, true);
    let (mut u, vt) = (svd.u?, svd.v_t?);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| svd.singular_values[j].total_cmp(&svd.singular_values[i]));
    // columns in the order of decreasing singular values
    let mut uu = M3::zeros();
    let mut vv = M3::zeros();
    let v = vt.transpose();
    for (k, &o) in order.iter().enumerate() {
        uu.set_column(k, &u.column(o).clone_owned());
        vv.set_column(k, &v.column(o).clone_owned());
    }
    u = uu;
    let mut v = vv;
    if u.determinant() < 0.0 {
        u = -u;
    }
    if v.determinant() < 0.0 {
        v = -v;
    }
    let w = M3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let t: V3 = u.column(2).into();
    let candidates =
        [(u * w * v.transpose(), t), (u * w * v.transpose(), -t), (u * w.transpose() * v.transpose(), t), (u * w.transpose() * v.transpose(), -t)];
    candidates
        .into_iter()
        .map(|(r, t)| ((0..a.len()).filter(|&i| in_front(&r, &t, &a[i], &b[i])).count(), r, t))
        .max_by_key(|c| c.0)
        .filter(|c| c.0 > 0)
        .map(|(_, r, t)| (r, t))
}

/// Whether the point seen along `a` in the query camera and `b` in the reference camera
/// (b ~ R X + t for X ~ a) lies in front of both: the depths of the least-squares
/// triangulation d_b b = d_a R a + t both positive.
fn in_front(r: &M3, t: &V3, a: &V3, b: &V3) -> bool {
    let ra = r * a;
    // [ra, -b] [da, db]^T = -t, normal equations
    let (p11, p12, p22) = (ra.dot(&ra), -ra.dot(b), b.dot(b));
    let (q1, q2) = (-ra.dot(t), b.dot(t));
    let det = p11 * p22 - p12 * p12;
    if det.abs() < 1e-15 {
        return false;
    }
    let da = (q1 * p22 - p12 * q2) / det;
    let db = (p11 * q2 - p12 * q1) / det;
    da > 0.0 && db > 0.0
}

/// The rotation nearest to taking rays `a` to rays `b` (unit vectors) in least squares: the
/// orthogonal Procrustes solution (Kabsch).
fn kabsch(a: &[V3], b: &[V3]) -> Option<M3> {
    let mut h = M3::zeros();
    for (x, y) in a.iter().zip(b) {
        h += y * x.transpose();
    }
    let svd = h.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let d = (u * vt).determinant().signum();
    Some(u * M3::from_diagonal(&V3::new(1.0, 1.0, d)) * vt)
}

/// The correspondences a rotation alone explains (angle between b and R a within `threshold`
/// radians), R found by a RANSAC of 2-ray samples and refitted on its inliers.
fn rotation_only_inliers(a: &[V3], b: &[V3], threshold: f64, seed: u64) -> usize {
    let n = a.len();
    if n < 2 {
        return 0;
    }
    let (ua, ub): (Vec<V3>, Vec<V3>) = a.iter().zip(b).map(|(x, y)| (x.normalize(), y.normalize())).unzip();
    let within = |r: &M3| -> Vec<usize> { (0..n).filter(|&i| (r * ua[i]).cross(&ub[i]).norm() < threshold).collect() };
    let mut rng = SplitMix64::new(seed ^ 0x5eed_2a7e);
    let mut best: Vec<usize> = vec![];
    for _ in 0..ROTATION_SAMPLES {
        let (i, j) = (rng.below(n), rng.below(n));
        if i == j {
            continue;
        }
        let Some(r) = kabsch(&[ua[i], ua[j]], &[ub[i], ub[j]]) else { continue };
        let mut inl = within(&r);
        if inl.len() <= best.len() {
            continue;
        }
        // refit on the inliers while that gathers more
        for _ in 0..REFINE_ROUNDS {
            let Some(g) = kabsch(&inl.iter().map(|&k| ua[k]).collect::<Vec<_>>(), &inl.iter().map(|&k| ub[k]).collect::<Vec<_>>()) else { break };
            let more = within(&g);
            if more.len() <= inl.len() {
                break;
            }
            inl = more;
        }
        best = inl;
    }
    best.len()
}

/// 2-ray samples of the rotation-only check.
const ROTATION_SAMPLES: usize = 64;

/// Levenberg-Marquardt over (R, t) on the Sampson distances of the correspondences: R moved by
/// a rotation vector, t within its tangent plane (renormalised), numeric derivatives. Returns
/// the start where no step lowers the cost.
fn refine(r0: M3, t0: V3, a: &[V3], b: &[V3]) -> (M3, V3) {
    let n = a.len();
    let residuals = |r: &M3, t: &V3| -> Vec<f64> {
        let e = skew(t) * r;
        (0..n)
            .map(|i| {
                let ea = e * a[i];
                let etb = e.transpose() * b[i];
                let d = (ea[0] * ea[0] + ea[1] * ea[1] + etb[0] * etb[0] + etb[1] * etb[1]).max(1e-300);
                b[i].dot(&ea) / d.sqrt()
            })
            .collect()
    };
    let cost = |res: &[f64]| res.iter().map(|v| v * v).sum::<f64>();
    // a tangent basis of t
    let tangent = |t: &V3| -> (V3, V3) {
        let helper = if t[0].abs() < 0.9 { V3::x() } else { V3::y() };
        let u = t.cross(&helper).normalize();
        (u, t.cross(&u))
    };
    let apply = |r: &M3, t: &V3, d: &[f64; 5]| -> (M3, V3) {
        let dr = nalgebra::Rotation3::new(V3::new(d[0], d[1], d[2])).into_inner();
        let (u, v) = tangent(t);
        ((dr * r), (t + u * d[3] + v * d[4]).normalize())
    };
    let (mut r, mut t) = (r0, t0);
    let mut res = residuals(&r, &t);
    let mut c = cost(&res);
    let mut mu = 1e-3;
    for _ in 0..LM_STEPS {
        let h = 1e-7;
        let cols: Vec<Vec<f64>> = (0..5)
            .map(|k| {
                let mut d = [0.0; 5];
                d[k] = h;
                let (rr, tt) = apply(&r, &t, &d);
                residuals(&rr, &tt).iter().zip(&res).map(|(x, y)| (x - y) / h).collect()
            })
            .collect();
        let jtj = SMatrix::<f64, 5, 5>::from_fn(|i, j| cols[i].iter().zip(&cols[j]).map(|(x, y)| x * y).sum());
        let jtr = SMatrix::<f64, 5, 1>::from_fn(|i, _| cols[i].iter().zip(&res).map(|(x, y)| x * y).sum());
        let mut improved = false;
        for _ in 0..8 {
            let mut damped = jtj;
            for i in 0..5 {
                damped[(i, i)] += mu * (jtj[(i, i)] + 1e-12);
            }
            let Some(step) = damped.lu().solve(&(-jtr)) else { break };
            let d = [step[0], step[1], step[2], step[3], step[4]];
            let (rr, tt) = apply(&r, &t, &d);
            let rres = residuals(&rr, &tt);
            let rc = cost(&rres);
            if rc.is_finite() && rc < c {
                (r, t, res, c) = (rr, tt, rres, rc);
                mu = (mu * 0.3).max(1e-12);
                improved = true;
                break;
            }
            mu *= 10.0;
        }
        if !improved {
            break;
        }
    }
    // keep R a rotation: the nearest one
    let svd = r.svd(true, true);
    if let (Some(u), Some(vt)) = (svd.u, svd.v_t) {
        let d = (u * vt).determinant().signum();
        r = u * M3::from_diagonal(&V3::new(1.0, 1.0, d)) * vt;
    }
    (r, t)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rot(axis: [f64; 3], deg: f64) -> M3 {
        nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(V3::new(axis[0], axis[1], axis[2])), deg.to_radians()).into_inner()
    }

    #[test]
    fn five_points_give_the_essential_matrix_that_made_them() {
        let r = rot([0.2, 1.0, 0.1], 12.0);
        let t = V3::new(0.8, -0.1, 0.3).normalize();
        let pts = [V3::new(0.3, -0.2, 5.0), V3::new(-1.0, 0.4, 7.0), V3::new(0.9, 0.8, 4.0), V3::new(-0.4, -0.9, 6.0), V3::new(0.1, 0.3, 9.0)];
        let a: [V3; 5] = pts.map(|x| x / x[2]);
        let b: [V3; 5] = pts.map(|x| {
            let y = r * x + t;
            y / y[2]
        });
        let truth = skew(&t) * r;
        let truth = truth / truth.norm();
        let found = five_point(&a, &b);
        assert!(!found.is_empty());
        let best = found.iter().map(|e| (e - truth).norm().min((e + truth).norm())).fold(f64::INFINITY, f64::min);
        assert!(best < 1e-6, "{best} from the true E among {} solutions", found.len());
        for e in &found {
            for i in 0..5 {
                assert!(b[i].dot(&(e * a[i])).abs() < 1e-8, "every solution satisfies the constraints");
            }
        }
    }

    #[test]
    fn the_decomposition_picks_the_pose_in_front_of_both_cameras() {
        let r = rot([1.0, 0.3, -0.2], 25.0);
        let t = V3::new(-0.2, 0.1, 1.0).normalize();
        let pts: Vec<V3> = (0..20).map(|i| V3::new((i % 5) as f64 - 2.0, (i / 5) as f64 - 1.5, 6.0 + (i % 3) as f64)).collect();
        let a: Vec<V3> = pts.iter().map(|x| x / x[2]).collect();
        let b: Vec<V3> = pts
            .iter()
            .map(|x| {
                let y = r * x + t;
                y / y[2]
            })
            .collect();
        let (rr, tt) = decompose(&(skew(&t) * r), &a, &b).unwrap();
        assert!((rr - r).norm() < 1e-9 && (tt - t).norm() < 1e-9, "{rr} {tt}");
    }
}
