//! `Matches`: the ranked references of a batch of queries, as padded numpy arrays and as lists.

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2};
use pyo3::prelude::*;
use semlook::matching::{QueryMatch, Setting};

/// Ranked references per query, best first. Arrays are [queries, longest list], padded with -1
/// (references) and NaN (scores); `counts` says how many entries of each row are real.
#[pyclass(frozen, module = "semlook._native", name = "Matches")]
pub struct PyMatches {
    setting: Setting,
    queries: Vec<String>,
    ranked: Vec<QueryMatch>,
    ids: Vec<Vec<String>>,
}

impl PyMatches {
    /// Matches with the id of every ranked reference from `id_of`.
    pub fn new(setting: Setting, queries: &[String], ranked: Vec<QueryMatch>, id_of: impl Fn(u32) -> String) -> Self {
        let ids = ranked.iter().map(|q| q.ranked.iter().map(|c| id_of(c.reference)).collect()).collect();
        PyMatches { setting, queries: queries.to_vec(), ranked, ids }
    }
    fn width(&self) -> usize {
        self.ranked.iter().map(|q| q.ranked.len()).max().unwrap_or(0)
    }
    /// Query `q` as a dict {query, top_k: [{reference, index, score, coarse, fine}]}.
    fn row(&self, q: usize) -> serde_json::Value {
        let top: Vec<serde_json::Value> = self.ranked[q]
            .ranked
            .iter()
            .zip(&self.ids[q])
            .map(|(c, id)| serde_json::json!({"reference": id, "index": c.reference, "score": c.score, "coarse": c.coarse, "fine": c.fine}))
            .collect();
        serde_json::json!({"query": self.queries[q], "top_k": top})
    }
    fn padded<T: Copy>(&self, pad: T, f: impl Fn(&semlook::matching::Candidate) -> T) -> Array2<T> {
        let w = self.width();
        let mut a = Array2::from_elem((self.ranked.len(), w), pad);
        for (q, m) in self.ranked.iter().enumerate() {
            for (j, c) in m.ranked.iter().enumerate() {
                a[(q, j)] = f(c);
            }
        }
        a
    }
}

#[pymethods]
impl PyMatches {
    fn __len__(&self) -> usize {
        self.ranked.len()
    }
    fn __repr__(&self) -> String {
        format!("Matches({} queries, setting {}, up to {} each)", self.ranked.len(), self.setting, self.width())
    }
    #[getter]
    fn setting(&self) -> &'static str {
        self.setting.name()
    }
    /// Query ids, in order.
    #[getter]
    fn queries(&self) -> Vec<String> {
        self.queries.clone()
    }
    /// Map indices of the ranked references, int64 [queries, L] (-1 padding).
    #[getter]
    fn references<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<i64>> {
        self.padded(-1, |c| c.reference as i64).into_pyarray(py)
    }
    /// Ranking scores, float32 [queries, L] (NaN padding).
    #[getter]
    fn scores<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f32>> {
        self.padded(f32::NAN, |c| c.score).into_pyarray(py)
    }
    /// SSIM of the global descriptors (NaN where the coarse stage did not run).
    #[getter]
    fn coarse<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f32>> {
        self.padded(f32::NAN, |c| c.coarse.unwrap_or(f32::NAN)).into_pyarray(py)
    }
    /// Tree-set similarity (NaN where the fine stage did not run).
    #[getter]
    fn fine<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f32>> {
        self.padded(f32::NAN, |c| c.fine.unwrap_or(f32::NAN)).into_pyarray(py)
    }
    /// Entries per query, int32 [queries].
    #[getter]
    fn counts<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i32>> {
        self.ranked.iter().map(|q| q.ranked.len() as i32).collect::<Vec<_>>().into_pyarray(py)
    }
    /// Per query, the ids of its ranked references (`references` as ids; `ids[q][0]` is query
    /// q's best match).
    #[getter]
    fn ids(&self) -> Vec<Vec<String>> {
        self.ids.clone()
    }
    /// Per query a dict {query, top_k: [{reference, score, coarse, fine}]}: the shape of
    /// `semlook query --json`'s "queries".
    fn to_list<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let rows: Vec<serde_json::Value> = (0..self.ranked.len()).map(|q| self.row(q)).collect();
        crate::arrays::to_py_object(py, &rows)
    }
    /// Query `q`'s dict (as `to_list()[q]`; negative indices count from the end).
    fn __getitem__<'py>(&self, py: Python<'py>, q: isize) -> PyResult<Bound<'py, PyAny>> {
        let n = self.ranked.len() as isize;
        let i = if q < 0 { q + n } else { q };
        if !(0..n).contains(&i) {
            return Err(pyo3::exceptions::PyIndexError::new_err(format!("query {q} of {n}")));
        }
        crate::arrays::to_py_object(py, &self.row(i as usize))
    }
    /// The queries' dicts in order (as `to_list()`).
    fn __iter__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, pyo3::types::PyIterator>> {
        self.to_list(py)?.try_iter()
    }
    /// `==` is [`equals`](Self::equals): the same rankings, ids and bit-identical scores.
    fn __eq__(&self, other: &Bound<'_, PyAny>) -> bool {
        other.cast::<PyMatches>().is_ok_and(|o| self.equals(o.get()))
    }
    /// Whether `other` ranks the same references with the same ids and bit-identical scores.
    fn equals(&self, other: &PyMatches) -> bool {
        let bits = |m: &PyMatches| -> Vec<Vec<(u32, u32, Option<u32>, Option<u32>)>> {
            m.ranked
                .iter()
                .map(|q| q.ranked.iter().map(|c| (c.reference, c.score.to_bits(), c.coarse.map(f32::to_bits), c.fine.map(f32::to_bits))).collect())
                .collect()
        };
        self.setting == other.setting && self.queries == other.queries && self.ids == other.ids && bits(self) == bits(other)
    }
}
