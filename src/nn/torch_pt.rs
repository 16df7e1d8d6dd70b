//! Reading a PyTorch state dict (`torch.save(model.state_dict())`, the zip format) without
//! Python: the archive's `data.pkl` is run on the crate's pickle machine ([`crate::nn::pickle`]), its
//! `torch._utils._rebuild_tensor_v2` calls name each tensor's storage, and each tensor is read
//! from its storage file `data/<key>` (little-endian).

use crate::error::{Error, Result};
use crate::nn::pickle::{Id, Node, Pickle};
use std::collections::HashMap;
use std::io::Read;
use std::path::Path;

/// Most bytes read for the pickle, and for one tensor storage: far above any keypoint network,
/// far below what a lying archive could make us allocate.
const MAX_PICKLE_BYTES: u64 = 64 << 20;
const MAX_STORAGE_BYTES: u64 = 1 << 30;

/// A float tensor (row-major, contiguous).
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    /// Size of each dimension, outermost first.
    pub shape: Vec<usize>,
    /// The values, row-major (the product of `shape` of them).
    pub data: Vec<f32>,
}

/// A tensor reference of a state dict: storage type, storage key, element count, offset, shape,
/// stride.
struct TensorRef {
    storage_type: String,
    key: String,
    numel: i64,
    offset: i64,
    shape: Vec<i64>,
    stride: Vec<i64>,
}

fn ints(p: &Pickle, id: Id) -> Result<Vec<i64>> {
    p.seq(id)
        .ok_or_else(|| Error::check("expected a tuple of ints"))?
        .iter()
        .map(|&i| p.int(i).ok_or_else(|| Error::check("expected an int")))
        .collect()
}

/// `torch._utils._rebuild_tensor_v2(storage, offset, shape, stride, ...)` with a persistent
/// storage id `('storage', StorageType, key, location, numel)`.
fn tensor_ref(p: &Pickle, id: Id) -> Result<Option<TensorRef>> {
    let Node::Call { func, args, .. } = p.node(id) else { return Ok(None) };
    if func != "torch._utils._rebuild_tensor_v2" {
        return Ok(None);
    }
    let arg = |i: usize| args.get(i).copied().ok_or_else(|| Error::check(format!("tensor rebuild has {} arguments", args.len())));
    let Node::Persistent(pid) = p.node(arg(0)?) else { return Err(Error::check("tensor without a persistent storage")) };
    let t = p.seq(*pid).ok_or_else(|| Error::check("persistent id is not a tuple"))?;
    let field = |i: usize| t.get(i).copied().ok_or_else(|| Error::check("persistent id is too short"));
    if p.str(field(0)?) != Some("storage") {
        return Err(Error::check("unsupported persistent id"));
    }
    let Node::Global(ty) = p.node(field(1)?) else { return Err(Error::check("storage type is not a global")) };
    Ok(Some(TensorRef {
        storage_type: ty.rsplit('.').next().unwrap_or("").to_string(),
        key: p.str(field(2)?).ok_or_else(|| Error::check("storage key is not a string"))?.to_string(),
        numel: p.int(field(4)?).ok_or_else(|| Error::check("storage size is not an int"))?,
        offset: p.int(arg(1)?).ok_or_else(|| Error::check("tensor offset is not an int"))?,
        shape: ints(p, arg(2)?)?,
        stride: ints(p, arg(3)?)?,
    }))
}

/// Reads every float tensor of a state dict (integer tensors such as `num_batches_tracked` are
/// skipped); an error is an [`Error::Model`] naming `path`.
pub fn read_state_dict(path: &Path) -> Result<HashMap<String, Tensor>> {
    read(path).map_err(|e| e.named(|reason| Error::Model { path: path.into(), reason }))
}

fn read(path: &Path) -> Result<HashMap<String, Tensor>> {
    let file = std::fs::File::open(path).map_err(|e| Error::check(e.to_string()))?;
    let mut zip = zip::ZipArchive::new(file).map_err(|e| Error::check(format!("not a PyTorch zip archive: {e}")))?;
    let names: Vec<String> = zip.file_names().filter_map(|s| s.ok().map(|s| s.to_string())).collect();
    let pkl = names.iter().find(|n| n.ends_with("/data.pkl") || *n == "data.pkl").ok_or_else(|| Error::check("no data.pkl in the archive"))?.clone();
    let prefix = pkl.trim_end_matches("data.pkl").to_string();
    let mut bytes = Vec::new();
    let entry = zip.by_name(&pkl).map_err(|e| Error::check(e.to_string()))?;
    entry.take(MAX_PICKLE_BYTES + 1).read_to_end(&mut bytes).map_err(|e| Error::check(format!("{pkl}: {e}")))?;
    if bytes.len() as u64 > MAX_PICKLE_BYTES {
        return Err(Error::check(format!("{pkl} is larger than {MAX_PICKLE_BYTES} bytes")));
    }
    let p = Pickle::load(&bytes)?;
    let entries = p.pairs(p.root).ok_or_else(|| Error::check("the pickle does not hold a dict"))?;
    let mut out = HashMap::new();
    for &(k, v) in entries {
        let (Some(name), Some(t)) = (p.str(k), tensor_ref(&p, v)?) else { continue };
        let name = name.to_string();
        let TensorRef { storage_type, key, numel, offset, shape, stride } = t;
        if storage_type != "FloatStorage" {
            continue;
        }
        let as_sizes = |v: &[i64]| v.iter().map(|&d| usize::try_from(d).ok()).collect::<Option<Vec<usize>>>();
        let (Ok(numel), Ok(offset), Some(shape), Some(stride)) = (u64::try_from(numel), usize::try_from(offset), as_sizes(&shape), as_sizes(&stride))
        else {
            return Err(Error::check(format!("{name}: negative size, offset, shape or stride")));
        };
        if shape.len() != stride.len() {
            return Err(Error::check(format!("{name}: shape {shape:?} and stride {stride:?} of different lengths")));
        }
        let want = numel
            .checked_mul(4)
            .filter(|&b| b <= MAX_STORAGE_BYTES)
            .ok_or_else(|| Error::check(format!("{name}: storage of {numel} floats is larger than {MAX_STORAGE_BYTES} bytes")))?;
        let count = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).filter(|&c| c as u64 <= numel);
        let count = count.ok_or_else(|| Error::check(format!("{name}: shape {shape:?} holds more values than its storage ({numel})")))?;
        let mut raw = Vec::new();
        // read at most one byte more than the storage should hold: a lying archive cannot make us allocate more
        zip.by_name(&format!("{prefix}data/{key}"))
            .map_err(|e| Error::check(format!("{name}: storage {key}: {e}")))?
            .take(want + 1)
            .read_to_end(&mut raw)
            .map_err(|e| Error::check(format!("{name}: storage {key}: {e}")))?;
        if raw.len() as u64 != want {
            return Err(Error::check(format!("{name}: storage {key} holds {} bytes, expected {want}", raw.len())));
        }
        let all: Vec<f32> = raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        // gather by strides (state dicts are contiguous, but do not assume it)
        let leaves = || format!("{name}: shape {shape:?}, stride {stride:?} and offset {offset} leave the storage ({numel} values)");
        let mut data = Vec::with_capacity(count);
        let mut idx = vec![0usize; shape.len()];
        for _ in 0..count {
            let at = idx.iter().zip(&stride).try_fold(offset, |a, (&i, &s)| i.checked_mul(s).and_then(|v| v.checked_add(a)));
            data.push(*at.and_then(|at| all.get(at)).ok_or_else(|| Error::check(leaves()))?);
            for d in (0..shape.len()).rev() {
                idx[d] += 1;
                if idx[d] < shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        out.insert(name, Tensor { shape, data });
    }
    Ok(out)
}
