//! The index model: the reduction (an orthonormal basis of the top `dims` directions of the
//! map's appearance vectors, by subspace iteration) and the lists' centroids (spherical k-means
//! on the reduced sample), trained from a seed, so the same map and parameters give the same
//! bytes. Stored as `index-model-<sha>.safetensors` (tensors `basis` `[dims, width]` f32 and
//! `centroids` `[lists, dims]` f32).

use super::codes::Codes;
use crate::error::{Error, Result};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// How an index is built (recorded in the map's manifest).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct IndexParams {
    /// Reduced dimensions.
    pub dims: usize,
    /// Lists (centroids).
    pub lists: usize,
    /// Vectors sampled from the map to train on (evenly spaced over the live images).
    pub sample: usize,
    /// Subspace and k-means iterations.
    pub iterations: usize,
    /// Seed of the starting basis and centroids.
    pub seed: u64,
    /// Pooling factor of the global descriptors' thumbnails kept beside the codes
    /// ([`super::thumb`]); 0: none (as every index built before thumbnails, whose manifests
    /// lack the field and keep their checksums).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub thumbnail: usize,
}

fn is_zero(v: &usize) -> bool {
    *v == 0
}

impl IndexParams {
    /// The build parameters of the `[index]` section for a map of `images` live images (`lists`
    /// 0: 4 sqrt(images) rounded to a power of two, 16 to 4,096).
    pub fn from_config(c: &crate::config::IndexConfig, images: usize) -> IndexParams {
        let lists = match c.lists {
            0 => (4.0 * (images as f64).sqrt()).max(1.0).log2().round().exp2().clamp(16.0, 4096.0) as usize,
            n => n,
        };
        IndexParams { dims: c.dims, lists, sample: c.sample, iterations: c.iterations, seed: c.seed, thumbnail: c.thumbnail }
    }
}

/// A trained model.
#[derive(Debug, Clone, PartialEq)]
pub struct Model {
    /// Values of the vectors it reduces.
    pub width: usize,
    /// Reduced dimensions.
    pub dims: usize,
    /// `[dims, width]`, orthonormal rows.
    pub basis: Vec<f32>,
    /// `[lists, dims]`, unit rows.
    pub centroids: Vec<f32>,
}

/// A small deterministic generator (splitmix64): the starting basis and centroids.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in [-1, 1).
    fn unit(&mut self) -> f32 {
        ((self.next() >> 40) as f32 / (1u64 << 23) as f32) - 1.0
    }
}

/// `out[m, n] = a[m, k] x b^T` where `b` is `[n, k]` (rows of both contiguous), rayon over
/// bands of rows of `a`.
pub(crate) fn matmul_bt(a: &[f32], m: usize, k: usize, b: &[f32], n: usize, out: &mut [f32]) {
    debug_assert!(a.len() >= m * k && b.len() >= n * k && out.len() >= m * n);
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        out[..m * n].fill(0.0);
        return;
    }
    const BAND: usize = 64;
    out[..m * n].par_chunks_mut(BAND * n).enumerate().for_each(|(c, o)| {
        let rows = o.len() / n;
        let a = &a[c * BAND * k..(c * BAND + rows) * k];
        // SAFETY: a is rows x k (row stride k), b^T is k x n read through b's strides (column
        // stride k), o is rows x n (row stride n); all three slices hold those extents.
        unsafe {
            matrixmultiply::sgemm(rows, k, n, 1.0, a.as_ptr(), k as isize, 1, b.as_ptr(), 1, k as isize, 0.0, o.as_mut_ptr(), n as isize, 1);
        }
    });
}

/// `out[m, n] = a^T x b` where `a` is `[k, m]` and `b` is `[k, n]`: the sum over `k` rows of
/// outer products, rayon over bands of the output's rows.
fn matmul_at(a: &[f32], k: usize, m: usize, b: &[f32], n: usize, out: &mut [f32]) {
    if m == 0 || n == 0 {
        return;
    }
    const BAND: usize = 16;
    out[..m * n].par_chunks_mut(BAND * n).enumerate().for_each(|(c, o)| {
        let rows = o.len() / n;
        // SAFETY: a^T's band is rows x k read from a with row stride 1 and column stride m
        // (offset c * BAND columns of a), b is k x n (row stride n), o is rows x n.
        unsafe {
            matrixmultiply::sgemm(
                rows,
                k,
                n,
                1.0,
                a.as_ptr().add(c * BAND),
                1,
                m as isize,
                b.as_ptr(),
                n as isize,
                1,
                0.0,
                o.as_mut_ptr(),
                n as isize,
                1,
            );
        }
    });
}

/// Orthonormalises the rows of `q` (`[r, w]`) in place by modified Gram-Schmidt, each row
/// projected out twice (one pass leaves a row that was nearly spanned by the earlier ones far from
/// orthogonal: "twice is enough", Giraud et al. 2005); a row that vanishes is replaced by an axis
/// that is orthogonalised the same way.
fn orthonormalise(q: &mut [f32], r: usize, w: usize) {
    let project_out = |q: &mut [f32], i: usize| {
        let (done, rest) = q.split_at_mut(i * w);
        let row = &mut rest[..w];
        for _ in 0..2 {
            for j in 0..i {
                let prev = &done[j * w..(j + 1) * w];
                let d: f64 = prev.iter().zip(row.iter()).map(|(a, b)| *a as f64 * *b as f64).sum();
                for (x, p) in row.iter_mut().zip(prev) {
                    *x = (*x as f64 - d * *p as f64) as f32;
                }
            }
        }
        row.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt()
    };
    for i in 0..r {
        let before = q[i * w..(i + 1) * w].iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
        let mut norm = project_out(q, i);
        let mut axis = i;
        // nothing left of the row (or far below what it was): an axis instead, the next one
        // until one is not spanned already
        while norm <= 1e-6 * before.max(1e-30) || norm < 1e-12 {
            let row = &mut q[i * w..(i + 1) * w];
            row.fill(0.0);
            row[axis % w] = 1.0;
            axis += 1;
            norm = project_out(q, i);
            if axis > i + w {
                break;
            }
        }
        let row = &mut q[i * w..(i + 1) * w];
        row.iter_mut().for_each(|x| *x = (*x as f64 / norm.max(1e-30)) as f32);
    }
}

fn normalise(v: &mut [f32]) {
    let n = v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    if n > 0.0 {
        v.iter_mut().for_each(|x| *x = (*x as f64 / n) as f32);
    }
}

impl Model {
    /// Trains a model on `sample` (`n` vectors of `width` values, row-major): `params.dims`
    /// directions (at most `width` and `n`) and `params.lists` centroids (at most `n`).
    pub fn train(sample: &[f32], n: usize, width: usize, params: &IndexParams) -> Result<Model> {
        if n == 0 || width == 0 || sample.len() != n * width {
            return Err(Error::check(format!("an index needs appearance vectors to train on ({n} of {width} values given)")));
        }
        if sample.iter().any(|v| !v.is_finite()) {
            return Err(Error::check("the training vectors hold NaN or infinity"));
        }
        let dims = params.dims.clamp(1, width.min(n));
        let lists = params.lists.clamp(1, n.min(u16::MAX as usize + 1));
        let mut rng = Rng(params.seed);
        // the basis: subspace iteration from a random start, q <- orth((X^T X) q)
        let mut q: Vec<f32> = (0..dims * width).map(|_| rng.unit()).collect();
        orthonormalise(&mut q, dims, width);
        let mut z = vec![0.0f32; n * dims];
        for _ in 0..params.iterations.max(1) {
            matmul_bt(sample, n, width, &q, dims, &mut z); // z = X q^T  [n, dims]
            matmul_at(&z, n, dims, sample, width, &mut q); // q = z^T X  [dims, width]
            orthonormalise(&mut q, dims, width);
        }
        // the lists: spherical k-means on the reduced sample
        matmul_bt(sample, n, width, &q, dims, &mut z);
        let mut centroids = Vec::with_capacity(lists * dims);
        // start from `lists` sample vectors spread by a seeded stride
        let stride = (n / lists).max(1);
        let offset = (rng.next() as usize) % stride;
        for l in 0..lists {
            let i = (offset + l * stride) % n;
            centroids.extend_from_slice(&z[i * dims..(i + 1) * dims]);
        }
        centroids.chunks_mut(dims).for_each(normalise);
        let mut sims = vec![0.0f32; n * lists];
        for _ in 0..params.iterations.max(1) {
            matmul_bt(&z, n, dims, &centroids, lists, &mut sims);
            let assign: Vec<(usize, f32)> = sims.chunks(lists).map(argmax).collect();
            let mut sums = vec![0.0f64; lists * dims];
            let mut counts = vec![0usize; lists];
            for (i, &(l, _)) in assign.iter().enumerate() {
                counts[l] += 1;
                for (s, v) in sums[l * dims..(l + 1) * dims].iter_mut().zip(&z[i * dims..(i + 1) * dims]) {
                    *s += *v as f64;
                }
            }
            // an empty list takes the vector its centroid fits worst (each at most once)
            let mut worst: Vec<usize> = (0..n).collect();
            worst.sort_by(|&a, &b| assign[a].1.total_cmp(&assign[b].1).then(a.cmp(&b)));
            let mut next_worst = worst.into_iter();
            for l in 0..lists {
                let c = &mut centroids[l * dims..(l + 1) * dims];
                if counts[l] == 0 {
                    if let Some(i) = next_worst.next() {
                        c.copy_from_slice(&z[i * dims..(i + 1) * dims]);
                    }
                } else {
                    for (x, s) in c.iter_mut().zip(&sums[l * dims..(l + 1) * dims]) {
                        *x = *s as f32;
                    }
                }
                normalise(c);
            }
        }
        Ok(Model { width, dims, basis: q, centroids })
    }

    /// Lists of the model.
    pub fn lists(&self) -> usize {
        self.centroids.len() / self.dims.max(1)
    }

    /// The reduced vector of `v` (`width` values): the basis times `v`.
    pub fn reduce(&self, v: &[f32]) -> Vec<f32> {
        (0..self.dims).map(|d| self.basis[d * self.width..(d + 1) * self.width].iter().zip(v).map(|(a, b)| a * b).sum()).collect()
    }

    /// The inner product of centroid `l` with a reduced vector.
    pub fn centroid_dot(&self, l: usize, y: &[f32]) -> f32 {
        self.centroids[l * self.dims..(l + 1) * self.dims].iter().zip(y).map(|(a, b)| a * b).sum()
    }

    /// The codes of `n` vectors (`width` values each, row-major): each one's list, and its
    /// reduced vector as int8 with one scale (largest magnitude / 127; the error of a value is at
    /// most half its scale).
    pub fn encode(&self, vectors: &[f32], n: usize) -> Codes {
        let mut y = vec![0.0f32; n * self.dims];
        matmul_bt(vectors, n, self.width, &self.basis, self.dims, &mut y);
        let lists = self.lists();
        let mut sims = vec![0.0f32; n * lists];
        matmul_bt(&y, n, self.dims, &self.centroids, lists, &mut sims);
        let mut out = Codes::with_capacity(n, self.dims);
        for i in 0..n {
            let (l, _) = argmax(&sims[i * lists..(i + 1) * lists]);
            out.push(l as u16, &y[i * self.dims..(i + 1) * self.dims]);
        }
        out
    }

    /// The model file's bytes (safetensors).
    pub fn file_bytes(&self) -> Result<Vec<u8>> {
        use safetensors::tensor::{Dtype, TensorView};
        let basis = TensorView::new(Dtype::F32, vec![self.dims, self.width], bytemuck::cast_slice(&self.basis));
        let cent = TensorView::new(Dtype::F32, vec![self.lists(), self.dims], bytemuck::cast_slice(&self.centroids));
        let (basis, cent) = match (basis, cent) {
            (Ok(b), Ok(c)) => (b, c),
            _ => return Err(Error::check("the index model's tensors do not fill their shapes")),
        };
        let meta = std::collections::HashMap::from([("format".to_string(), "semlook-map-index-model 1".to_string())]);
        safetensors::serialize(vec![("basis", basis), ("centroids", cent)], Some(meta))
            .map_err(|e| Error::check(format!("index model does not serialise: {e}")))
    }

    /// A model from its file's bytes, checked: tensors, shapes (`width` values reduced to `dims`,
    /// `lists` centroids), finite values.
    pub fn from_bytes(bytes: &[u8], width: usize, dims: usize, lists: usize) -> Result<Model> {
        let st = safetensors::SafeTensors::deserialize(bytes).map_err(|e| Error::check(format!("not an index model: {e}")))?;
        let get = |name: &str, shape: [usize; 2]| -> Result<Vec<f32>> {
            let t = st.tensor(name).map_err(|_| Error::check(format!("no {name} tensor")))?;
            if t.dtype() != safetensors::tensor::Dtype::F32 || t.shape() != shape {
                return Err(Error::check(format!("{name} is {:?} {:?}, the manifest says f32 {shape:?}", t.dtype(), t.shape())));
            }
            let v: Vec<f32> = bytemuck::pod_collect_to_vec(t.data());
            if v.iter().any(|x| !x.is_finite()) {
                return Err(Error::check(format!("{name} holds NaN or infinity")));
            }
            Ok(v)
        };
        Ok(Model { width, dims, basis: get("basis", [dims, width])?, centroids: get("centroids", [lists, dims])? })
    }
}

/// The index and value of the largest entry (the first of equal ones); (0, -inf) for none.
fn argmax(v: &[f32]) -> (usize, f32) {
    v.iter().enumerate().fold((0, f32::NEG_INFINITY), |b, (i, &x)| if x > b.1 { (i, x) } else { b })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Vectors near `centres` random unit directions in `width` dimensions, unit length.
    pub(crate) fn clustered(n: usize, width: usize, centres: usize, spread: f32, seed: u64) -> Vec<f32> {
        let mut rng = Rng(seed);
        let c: Vec<f32> = (0..centres * width).map(|_| rng.unit()).collect();
        let mut out = Vec::with_capacity(n * width);
        for i in 0..n {
            let k = i % centres;
            let mut v: Vec<f32> = (0..width).map(|d| c[k * width + d] + spread * rng.unit()).collect();
            normalise(&mut v);
            out.extend(v);
        }
        out
    }

    fn params() -> IndexParams {
        IndexParams { dims: 16, lists: 8, sample: 4096, iterations: 6, seed: 7, thumbnail: 0 }
    }

    #[test]
    fn the_basis_is_orthonormal_and_spans_the_data() {
        // data in a 6-dimensional subspace of 40 dimensions: 16 directions capture all of it
        let (n, w) = (300, 40);
        let mut rng = Rng(3);
        let dirs: Vec<f32> = (0..6 * w).map(|_| rng.unit()).collect();
        let x: Vec<f32> = (0..n)
            .flat_map(|_| {
                let a: Vec<f32> = (0..6).map(|_| rng.unit()).collect();
                (0..w).map(|d| (0..6).map(|k| a[k] * dirs[k * w + d]).sum::<f32>()).collect::<Vec<f32>>()
            })
            .collect();
        let m = Model::train(&x, n, w, &params()).unwrap();
        for i in 0..m.dims {
            for j in 0..m.dims {
                let d: f32 = (0..w).map(|k| m.basis[i * w + k] * m.basis[j * w + k]).sum();
                assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-4, "rows {i}, {j}: {d}");
            }
        }
        // projecting and lifting back loses nothing of a data vector
        for i in 0..5 {
            let v = &x[i * w..(i + 1) * w];
            let y = m.reduce(v);
            let back: Vec<f32> = (0..w).map(|k| (0..m.dims).map(|d| y[d] * m.basis[d * w + k]).sum()).collect();
            let err: f32 = back.iter().zip(v).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
            assert!(err < 1e-3, "vector {i}: {err}");
        }
    }

    #[test]
    fn training_is_deterministic_and_lists_follow_the_clusters() {
        let (n, w) = (400, 32);
        let x = clustered(n, w, 8, 0.05, 11);
        let a = Model::train(&x, n, w, &params()).unwrap();
        let b = Model::train(&x, n, w, &params()).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.file_bytes().unwrap(), b.file_bytes().unwrap());
        let codes = a.encode(&x, n);
        // vectors of one cluster share a list
        for i in 0..n {
            assert_eq!(codes.lists[i], codes.lists[i % 8], "vector {i}");
        }
        let back = Model::from_bytes(&a.file_bytes().unwrap(), w, a.dims, a.lists()).unwrap();
        assert_eq!(back, a);
        assert!(Model::from_bytes(&a.file_bytes().unwrap(), w + 1, a.dims, a.lists()).is_err());
    }

    #[test]
    fn no_vectors_is_an_error_and_few_vectors_shrink_the_model() {
        assert!(Model::train(&[], 0, 8, &params()).is_err());
        assert!(Model::train(&[f32::NAN; 8], 1, 8, &params()).is_err());
        let x = clustered(3, 8, 3, 0.1, 1);
        let m = Model::train(&x, 3, 8, &params()).unwrap();
        assert_eq!((m.dims, m.lists()), (3, 3));
        assert_eq!(m.encode(&[], 0).len(), 0);
    }
}
