//! Sharded matching: `Shard` opens a range of a map's segments (what one Ray actor serves) and
//! gives candidate lists in the whole map's index space and fine scores for pairs it owns;
//! `merge_candidates` and `rank` are what the driver runs. Candidate lists travel as padded
//! arrays: scores float32 [Q, L], references int64 [Q, L] (-1 padding), counts int32 [Q].

use crate::arrays::to_py_object;
use crate::arrays::{fusion, pool, setting};
use crate::descriptors::PyDescriptors;
use crate::encoder::PyConfig;
use crate::engine::{engine_for, run};
use crate::errors::{invalid, OrPy};
use crate::map::query_config;
use crate::matches::PyMatches;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use rayon::ThreadPool;
use semlook::config::Config;
use semlook::descriptors::source::RefSource;
use semlook::engine::Engine;
use semlook::map::{shard, Map};
use semlook::matching;
use semlook::matching::merge_lists;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

type Lists = Vec<Vec<(f32, u32)>>;
type ListArrays<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<i64>>, Bound<'py, PyArray1<i32>>);

fn to_arrays<'py>(py: Python<'py>, lists: &Lists, width: usize) -> ListArrays<'py> {
    let mut s = Array2::from_elem((lists.len(), width), f32::NAN);
    let mut r = Array2::from_elem((lists.len(), width), -1i64);
    for (q, l) in lists.iter().enumerate() {
        for (j, &(score, i)) in l.iter().enumerate().take(width) {
            s[(q, j)] = score;
            r[(q, j)] = i as i64;
        }
    }
    let counts: Vec<i32> = lists.iter().map(|l| l.len().min(width) as i32).collect();
    (s.into_pyarray(py), r.into_pyarray(py), counts.into_pyarray(py))
}

fn from_arrays(scores: &PyReadonlyArray2<'_, f32>, refs: &PyReadonlyArray2<'_, i64>, counts: &PyReadonlyArray1<'_, i32>) -> PyResult<Lists> {
    let (s, r, c) = (scores.as_array(), refs.as_array(), counts.as_array());
    if s.shape() != r.shape() || c.len() != s.shape()[0] {
        return Err(invalid("candidate arrays", format!("scores {:?}, references {:?}, counts {:?} disagree", s.shape(), r.shape(), c.shape())));
    }
    (0..c.len())
        .map(|q| {
            let n = usize::try_from(c[q])
                .ok()
                .filter(|&n| n <= s.shape()[1])
                .ok_or_else(|| invalid("candidate arrays", format!("count {} of query {q}", c[q])))?;
            (0..n)
                .map(|j| {
                    u32::try_from(r[(q, j)])
                        .map(|i| (s[(q, j)], i))
                        .map_err(|_| invalid("candidate arrays", format!("reference {} of query {q}", r[(q, j)])))
                })
                .collect()
        })
        .collect()
}

/// One shard of a map: the segments `seg_start..seg_end` opened alone (memory-mapped). Methods
/// run on a pool of `threads` threads of its own (rayon ignores Ray's CPU limits), on `backend`
/// ("cpu", "gpu" or "auto"; None: `DEFAULT_BACKEND`; as `Engine`, on GPU `adapter`; on a GPU the
/// shard's part of the map stays resident).
#[pyclass(frozen, module = "semlook._native", name = "Shard")]
pub struct PyShard {
    map: Arc<Map>,
    spec: shard::ShardSpec,
    cfg: Config,
    pool: Option<Arc<ThreadPool>>,
    engine: Arc<Mutex<Engine>>,
}

#[pymethods]
impl PyShard {
    /// Opens the shard; with `generation`, fails if the map changed since it was planned.
    /// `config_toml` as `Config(toml)` (default: the map's), `k` candidates per query.
    #[new]
    #[pyo3(signature = (map_dir, seg_start, seg_end, generation=None, config_toml=None, k=None, threads=None, backend=None, adapter=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        map_dir: PathBuf,
        seg_start: usize,
        seg_end: usize,
        generation: Option<u64>,
        config_toml: Option<&str>,
        k: Option<usize>,
        threads: Option<usize>,
        backend: Option<&str>,
        adapter: Option<usize>,
    ) -> PyResult<Self> {
        let (map, spec) = py.detach(|| Map::open_range(&map_dir, seg_start..seg_end, generation)).py_err()?;
        let config = config_toml.map(|t| Config::from_toml(t, "config_toml")).transpose().py_err()?;
        let cfg = query_config(&map, config, k)?;
        let engine = Arc::new(Mutex::new(engine_for(py, backend, adapter)?.0));
        Ok(PyShard { map: Arc::new(map), spec, cfg, pool: pool(threads)?, engine })
    }
    /// The shard's engine: "cpu (N threads of its pool)" or "gpu: adapter (...)".
    #[getter]
    fn backend(&self, py: Python<'_>) -> PyResult<String> {
        run(py, self.pool.clone(), Some(&self.engine), |e| Ok(e.describe()))
    }
    /// Calls this shard completed on the GPU (see `Engine.gpu_calls`).
    #[getter]
    fn gpu_calls(&self, py: Python<'_>) -> u64 {
        py.detach(|| self.engine.lock().map_or(0, |e| e.gpu_calls()))
    }
    /// Each query's candidates in the whole map's index space (see `list_len`).
    fn candidates<'py>(&self, py: Python<'py>, queries: &PyDescriptors, setting: &str) -> PyResult<ListArrays<'py>> {
        let s = self::setting(setting)?;
        let (map, set, cfg, start) = (self.map.clone(), queries.inner.clone(), &self.cfg, self.spec.global_start as u32);
        let (lists, _) = run(py, self.pool.clone(), Some(&self.engine), |e| e.candidates(map.as_ref(), &set, s, cfg))?;
        let lists: Lists = lists.into_iter().map(|l| l.into_iter().map(|(sc, r)| (sc, r + start)).collect()).collect();
        Ok(to_arrays(py, &lists, matching::list_len(s, cfg)))
    }
    /// Fine scores of pairs (query index `q[i]`, whole-map reference `r[i]`), all owned here:
    /// float32 [n, 5], per pair its fine score, its inliers (-1: not verified), its compact
    /// HOGs' cosine (NaN: none), the inliers' tail probability under the map's null and the
    /// compact HOGs' likelihood ratio against it (NaN: not tested), what `rank` weighs.
    fn fine<'py>(
        &self,
        py: Python<'py>,
        queries: &PyDescriptors,
        setting: &str,
        q: PyReadonlyArray1<'_, u32>,
        r: PyReadonlyArray1<'_, i64>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let s = self::setting(setting)?;
        if q.len() != r.len() {
            return Err(invalid("pairs", format!("{} queries and {} references", q.len(), r.len())));
        }
        let range = self.spec.global_start as i64..(self.spec.global_start + self.spec.len) as i64;
        let pairs = q
            .as_array()
            .iter()
            .zip(r.as_array().iter())
            .map(|(&q, &r)| match range.contains(&r) {
                true => Ok((q, (r - range.start) as u32)),
                false => Err(invalid("pairs", format!("reference {r} is not in this shard ({range:?})"))),
            })
            .collect::<PyResult<Vec<_>>>()?;
        let (map, set, cfg) = (self.map.clone(), queries.inner.clone(), &self.cfg);
        let f = run(py, self.pool.clone(), Some(&self.engine), |e| e.fine_scores(map.as_ref(), &set, s, cfg, &pairs))?;
        let rows: Vec<f32> = f
            .iter()
            .flat_map(|p| {
                let nan = |v: Option<f32>| v.unwrap_or(f32::NAN);
                [p.fine, p.inliers.map_or(-1.0, |i| i as f32), nan(p.compact_hog), nan(p.p_inliers), nan(p.compact_hog_ratio)]
            })
            .collect();
        Ok(Array2::from_shape_vec((f.len(), 5), rows).map_err(|e| invalid("fine", e.to_string()))?.into_pyarray(py))
    }
    /// Ids of whole-map references `r`, all owned here.
    fn reference_ids(&self, r: Vec<i64>) -> PyResult<Vec<String>> {
        let start = self.spec.global_start as i64;
        r.iter()
            .map(|&i| match (i - start) as usize {
                j if i >= start && j < self.map.len() => Ok(self.map.id(j).to_string()),
                _ => Err(invalid("reference_ids", format!("reference {i} is not in this shard"))),
            })
            .collect()
    }
    /// {segments, global_start, len, generation}.
    fn info<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py_object(py, &self.spec)
    }
}

/// Cuts the map in `map_dir` into `shards` contiguous segment ranges of about equal images: a
/// list of {segments: {start, end}, global_start, len, generation}. Reads the manifest only.
#[pyfunction]
pub fn plan_shards<'py>(py: Python<'py>, map_dir: PathBuf, shards: usize) -> PyResult<Bound<'py, PyAny>> {
    let m = semlook::map::manifest::read_existing(&map_dir).py_err()?;
    to_py_object(py, &shard::plan(&m, shards).py_err()?)
}

/// The global candidate lists from per-shard ones (each as `Shard.candidates` returns them):
/// exactly the lists one process computes over the whole map, ties to the lower index.
#[pyfunction]
pub fn merge_candidates<'py>(
    py: Python<'py>,
    parts: Vec<(PyReadonlyArray2<'py, f32>, PyReadonlyArray2<'py, i64>, PyReadonlyArray1<'py, i32>)>,
    k: usize,
) -> PyResult<ListArrays<'py>> {
    let lists = parts.iter().map(|(s, r, c)| from_arrays(s, r, c)).collect::<PyResult<Vec<_>>>()?;
    let views: Vec<&[Vec<(f32, u32)>]> = lists.iter().map(Vec::as_slice).collect();
    let merged = merge_lists(&views, k).map_err(|r| invalid("merge_candidates", r))?;
    Ok(to_arrays(py, &merged, k))
}

/// The final ranking of merged candidates, as `Map.query` returns it: `fine` holds what
/// `Shard.fine` gives every candidate in row order (float32 [n, 5], `Shard.fine`'s columns;
/// settings with both stages; else None), `ids` the id of every
/// candidate in the same order, `queries` the query ids.
#[pyfunction]
#[pyo3(signature = (setting, scores, references, counts, fine, queries, ids, fusion="fine", config=None))]
#[allow(clippy::too_many_arguments)]
pub fn rank(
    setting: &str,
    scores: PyReadonlyArray2<'_, f32>,
    references: PyReadonlyArray2<'_, i64>,
    counts: PyReadonlyArray1<'_, i32>,
    fine: Option<PyReadonlyArray2<'_, f32>>,
    queries: Vec<String>,
    ids: Vec<String>,
    fusion: &str,
    config: Option<PyRef<'_, PyConfig>>,
) -> PyResult<PyMatches> {
    let s = self::setting(setting)?;
    let lists = from_arrays(&scores, &references, &counts)?;
    if queries.len() != lists.len() {
        return Err(invalid("rank", format!("{} query ids for {} lists", queries.len(), lists.len())));
    }
    let pairs = matching::pairs_of(&lists);
    if ids.len() != pairs.len() {
        return Err(invalid("rank", format!("{} ids for {} candidates", ids.len(), pairs.len())));
    }
    let fine: Option<Vec<matching::PairScore>> = match fine {
        None => None,
        Some(f) if f.shape()[1] != 5 => return Err(invalid("rank", format!("fine holds {} columns, Shard.fine gives 5", f.shape()[1]))),
        Some(f) => Some(
            f.as_array()
                .rows()
                .into_iter()
                .map(|r| matching::PairScore {
                    fine: r[0],
                    inliers: (r[1] >= 0.0).then_some(r[1] as u32),
                    compact_hog: (!r[2].is_nan()).then_some(r[2]),
                    p_inliers: (!r[3].is_nan()).then_some(r[3]),
                    compact_hog_ratio: (!r[4].is_nan()).then_some(r[4]),
                })
                .collect(),
        ),
    };
    let mut cfg = config.map_or_else(Config::default, |c| c.inner.clone());
    cfg.matching.score = self::fusion(fusion)?;
    let ranked = matching::rank(s, &lists, fine.as_deref(), &cfg).py_err()?;
    let id_of: std::collections::HashMap<u32, String> = pairs.iter().map(|&(_, r)| r).zip(ids).collect();
    Ok(PyMatches::new(s, &queries, ranked, |r| id_of.get(&r).cloned().unwrap_or_default()))
}

/// Length of the candidate lists of `setting` under `config` (default: the defaults).
#[pyfunction]
#[pyo3(signature = (setting, config=None))]
pub fn list_len(setting: &str, config: Option<PyRef<'_, PyConfig>>) -> PyResult<usize> {
    Ok(matching::list_len(self::setting(setting)?, &config.map_or_else(Config::default, |c| c.inner.clone())))
}

/// Whether `setting` re-ranks coarse candidates by the fine stage (then `rank` takes fine scores).
#[pyfunction]
pub fn reranks(setting: &str) -> PyResult<bool> {
    Ok(self::setting(setting)?.reranks())
}

/// Names of the matching settings.
#[pyfunction]
pub fn settings() -> Vec<&'static str> {
    matching::Setting::ALL.iter().map(|s| s.name()).collect()
}
