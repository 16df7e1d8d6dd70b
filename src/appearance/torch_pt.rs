//! Reading a PyTorch state dict (`torch.save(model.state_dict())`, the zip format) without
//! Python: the archive's `data.pkl` is run on a minimal pickle machine that knows the opcodes a
//! state dict uses (protocol 2: dicts, tuples, ints, strings, `collections.OrderedDict`,
//! `torch._utils._rebuild_tensor_v2` and persistent storage ids), and each tensor is read from its
//! storage file `data/<key>` (little-endian).

use std::collections::HashMap;
use std::io::Read;
use std::path::Path;

/// A float tensor (row-major, contiguous).
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

#[derive(Debug, Clone)]
enum Val {
    None,
    Bool,
    Int(i64),
    Str(String),
    Tuple(Vec<Val>),
    Dict(Vec<(Val, Val)>),
    Global(String),
    /// storage type (e.g. "FloatStorage"), file key, element count
    Storage(String, String, i64),
    /// storage, offset, shape, stride
    Tensor(Box<Val>, i64, Vec<i64>, Vec<i64>),
    Mark,
}

fn ints(v: &Val) -> Result<Vec<i64>, String> {
    match v {
        Val::Tuple(items) => items.iter().map(|x| if let Val::Int(i) = x { Ok(*i) } else { Err("expected an int".to_string()) }).collect(),
        _ => Err("expected a tuple of ints".into()),
    }
}

/// Runs the pickle program of a state dict and returns its (name, value) entries.
fn unpickle(data: &[u8]) -> Result<Vec<(Val, Val)>, String> {
    let mut stack: Vec<Val> = Vec::new();
    let mut memo: HashMap<u32, Val> = HashMap::new();
    let mut pos = 0usize;
    let take = |pos: &mut usize, n: usize| -> Result<&[u8], String> {
        let s = data.get(*pos..*pos + n).ok_or("pickle ends early")?;
        *pos += n;
        Ok(s)
    };
    let pop_mark = |stack: &mut Vec<Val>| -> Result<Vec<Val>, String> {
        let m = stack.iter().rposition(|v| matches!(v, Val::Mark)).ok_or("MARK missing")?;
        let items = stack.split_off(m + 1);
        stack.pop();
        Ok(items)
    };
    let u32le = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    loop {
        let op = *take(&mut pos, 1)?.first().unwrap();
        match op {
            0x80 => {
                take(&mut pos, 1)?; // PROTO
            }
            b'c' => {
                // GLOBAL "module\nname\n"
                let rest = &data[pos..];
                let nl1 = rest.iter().position(|&b| b == b'\n').ok_or("bad GLOBAL")?;
                let nl2 = rest[nl1 + 1..].iter().position(|&b| b == b'\n').ok_or("bad GLOBAL")?;
                let module = String::from_utf8_lossy(&rest[..nl1]);
                let name = String::from_utf8_lossy(&rest[nl1 + 1..nl1 + 1 + nl2]);
                stack.push(Val::Global(format!("{module}.{name}")));
                pos += nl1 + nl2 + 2;
            }
            b'q' => {
                let i = take(&mut pos, 1)?[0] as u32;
                memo.insert(i, stack.last().ok_or("BINPUT on empty stack")?.clone());
            }
            b'r' => {
                let i = u32le(take(&mut pos, 4)?);
                memo.insert(i, stack.last().ok_or("LONG_BINPUT on empty stack")?.clone());
            }
            b'h' => {
                let i = take(&mut pos, 1)?[0] as u32;
                stack.push(memo.get(&i).cloned().ok_or("BINGET of an unknown memo")?);
            }
            b'j' => {
                let i = u32le(take(&mut pos, 4)?);
                stack.push(memo.get(&i).cloned().ok_or("LONG_BINGET of an unknown memo")?);
            }
            b')' => stack.push(Val::Tuple(vec![])),
            b'}' => stack.push(Val::Dict(vec![])),
            b'(' => stack.push(Val::Mark),
            b'N' => stack.push(Val::None),
            0x88 | 0x89 => stack.push(Val::Bool),
            b'K' => stack.push(Val::Int(take(&mut pos, 1)?[0] as i64)),
            b'M' => {
                let b = take(&mut pos, 2)?;
                stack.push(Val::Int(u16::from_le_bytes([b[0], b[1]]) as i64));
            }
            b'J' => stack.push(Val::Int(u32le(take(&mut pos, 4)?) as i32 as i64)),
            0x8a => {
                // LONG1
                let n = take(&mut pos, 1)?[0] as usize;
                let b = take(&mut pos, n)?;
                let mut v: i64 = 0;
                for (k, &byte) in b.iter().enumerate().take(8) {
                    v |= (byte as i64) << (8 * k);
                }
                if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                    v -= 1i64 << (8 * n);
                }
                stack.push(Val::Int(v));
            }
            b'X' => {
                let n = u32le(take(&mut pos, 4)?) as usize;
                stack.push(Val::Str(String::from_utf8_lossy(take(&mut pos, n)?).into_owned()));
            }
            b't' => {
                let items = pop_mark(&mut stack)?;
                stack.push(Val::Tuple(items));
            }
            0x85 | 0x86 | 0x87 => {
                let n = (op - 0x84) as usize;
                if stack.len() < n {
                    return Err("TUPLEn on a short stack".into());
                }
                let items = stack.split_off(stack.len() - n);
                stack.push(Val::Tuple(items));
            }
            b'Q' => {
                // BINPERSID: ('storage', StorageType, key, location, numel)
                let pid = stack.pop().ok_or("BINPERSID on empty stack")?;
                let Val::Tuple(t) = pid else { return Err("persistent id is not a tuple".into()) };
                match (t.first(), t.get(1), t.get(2), t.get(4)) {
                    (Some(Val::Str(s)), Some(Val::Global(ty)), Some(Val::Str(key)), Some(Val::Int(n))) if s == "storage" => {
                        stack.push(Val::Storage(ty.rsplit('.').next().unwrap_or("").to_string(), key.clone(), *n))
                    }
                    _ => return Err("unsupported persistent id".into()),
                }
            }
            b'R' => {
                let args = stack.pop().ok_or("REDUCE on empty stack")?;
                let f = stack.pop().ok_or("REDUCE without callable")?;
                let Val::Global(name) = f else { return Err("REDUCE of a non-global".into()) };
                let Val::Tuple(a) = args else { return Err("REDUCE arguments are not a tuple".into()) };
                let v = match name.as_str() {
                    "collections.OrderedDict" => Val::Dict(vec![]),
                    "torch._utils._rebuild_tensor_v2" => {
                        let storage = a.first().cloned().ok_or("tensor without storage")?;
                        let offset = match a.get(1) {
                            Some(Val::Int(o)) => *o,
                            _ => return Err("tensor offset".into()),
                        };
                        Val::Tensor(Box::new(storage), offset, ints(a.get(2).ok_or("tensor shape")?)?, ints(a.get(3).ok_or("tensor stride")?)?)
                    }
                    other => return Err(format!("unsupported callable {other}")),
                };
                stack.push(v);
            }
            b's' => {
                let v = stack.pop().ok_or("SETITEM")?;
                let k = stack.pop().ok_or("SETITEM")?;
                match stack.last_mut() {
                    Some(Val::Dict(d)) => d.push((k, v)),
                    _ => return Err("SETITEM on a non-dict".into()),
                }
            }
            b'u' => {
                let items = pop_mark(&mut stack)?;
                let Some(Val::Dict(d)) = stack.last_mut() else { return Err("SETITEMS on a non-dict".into()) };
                for kv in items.chunks(2) {
                    if let [k, v] = kv {
                        d.push((k.clone(), v.clone()));
                    }
                }
            }
            b'b' => {
                stack.pop().ok_or("BUILD")?; // object state (the OrderedDict's _metadata): not needed
            }
            b'.' => break,
            other => return Err(format!("unsupported pickle opcode 0x{other:02x} at byte {}", pos - 1)),
        }
    }
    match stack.pop() {
        Some(Val::Dict(d)) => Ok(d),
        _ => Err("the pickle does not hold a dict".into()),
    }
}

/// Reads every float tensor of a state dict (integer tensors such as `num_batches_tracked` are
/// skipped).
pub fn read_state_dict(path: &Path) -> Result<HashMap<String, Tensor>, String> {
    let file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let mut zip = zip::ZipArchive::new(file).map_err(|e| format!("not a PyTorch zip archive: {e}"))?;
    let names: Vec<String> = zip.file_names().filter_map(|s| s.ok().map(|s| s.to_string())).collect();
    let pkl = names.iter().find(|n| n.ends_with("/data.pkl") || *n == "data.pkl").ok_or("no data.pkl in the archive")?.clone();
    let prefix = pkl.trim_end_matches("data.pkl").to_string();
    let mut bytes = Vec::new();
    zip.by_name(&pkl).map_err(|e| e.to_string())?.read_to_end(&mut bytes).map_err(|e| e.to_string())?;
    let entries = unpickle(&bytes)?;
    let mut out = HashMap::new();
    for (k, v) in entries {
        let (Val::Str(name), Val::Tensor(storage, offset, shape, stride)) = (k, v) else { continue };
        let Val::Storage(ty, key, numel) = *storage else { return Err(format!("{name}: storage missing")) };
        if ty != "FloatStorage" {
            continue;
        }
        let mut raw = Vec::new();
        zip.by_name(&format!("{prefix}data/{key}"))
            .map_err(|e| format!("{name}: storage {key}: {e}"))?
            .read_to_end(&mut raw)
            .map_err(|e| e.to_string())?;
        if raw.len() != numel as usize * 4 {
            return Err(format!("{name}: storage {key} holds {} bytes, expected {}", raw.len(), numel * 4));
        }
        let all: Vec<f32> = raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let shape: Vec<usize> = shape.iter().map(|&s| s as usize).collect();
        let count: usize = shape.iter().product();
        // gather by strides (state dicts are contiguous, but do not assume it)
        let mut data = Vec::with_capacity(count);
        let mut idx = vec![0usize; shape.len()];
        for _ in 0..count {
            let at = offset + idx.iter().zip(&stride).map(|(&i, &s)| i as i64 * s).sum::<i64>();
            data.push(*all.get(at as usize).ok_or_else(|| format!("{name}: strides leave the storage"))?);
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
