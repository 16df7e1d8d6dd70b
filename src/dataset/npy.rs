//! VPR-Bench's ground truth, `ground_truth_new.npy`: a NumPy object array (saved with
//! `np.save`, so a `.npy` header followed by a pickle of the array) whose rows are
//! `[query_index, valid_reference_indices]`; the indices are Python ints, NumPy integer scalars,
//! lists of them, or NumPy integer arrays (as `np.where` returns them). Read with the crate's
//! pickle machine: no Python, no code execution.

use crate::error::{Error, Result};
use crate::nn::pickle::{Id, Node, Pickle};

/// Most ground-truth rows a file may hold (a guard against absurd shapes in damaged files).
const MAX_ROWS: usize = 100_000_000;
/// Reference indices read in all, per byte of the file (a memoised list named by many rows
/// would otherwise be copied once per row).
const INDICES_PER_BYTE: usize = 16;

/// Per query index, the valid reference indices, from the bytes of a `.npy` file.
/// What does not read is an [`Error::Check`] (the caller names the file).
pub fn read_ground_truth(bytes: &[u8]) -> Result<Vec<(u64, Vec<u64>)>> {
    let (descr, shape, data) = header(bytes)?;
    if descr != "|O" {
        return Err(Error::check(format!("dtype {descr:?}: expected an object array ('|O') of [query, [references]] rows")));
    }
    let p = Pickle::load(data).map_err(|e| e.named(|r| Error::check(format!("pickled array: {r}"))))?;
    let (arr_shape, items) = array(&p, p.root)?.ok_or_else(|| Error::check("the pickle does not hold a NumPy array"))?;
    if arr_shape != shape {
        return Err(Error::check(format!("the header says shape {shape:?}, the pickled array {arr_shape:?}")));
    }
    let items = match items {
        Items::Objects(v) => v,
        Items::Ints(_) => return Err(Error::check("the array holds plain integers, not [query, [references]] rows")),
    };
    let rows: Vec<(Id, Id)> = match arr_shape.as_slice() {
        // an (n, 2) object array: query, references
        [n, 2] if items.len() == 2 * n => items.chunks(2).map(|c| (c[0], c[1])).collect(),
        // an (n,) array of 2-element rows
        [n] if items.len() == *n => items
            .iter()
            .map(|&row| match ints_or_seq(&p, row)? {
                Some(Items::Objects(v)) if v.len() == 2 => Ok((v[0], v[1])),
                _ => Err(Error::check("a row is not a [query, references] pair")),
            })
            .collect::<Result<_>>()?,
        other => return Err(Error::check(format!("shape {other:?}: expected (n, 2) rows of [query, references]"))),
    };
    if rows.len() > MAX_ROWS {
        return Err(Error::check(format!("{} rows is more than the {MAX_ROWS} this reader accepts", rows.len())));
    }
    let mut budget = bytes.len().saturating_mul(INDICES_PER_BYTE).saturating_add(1 << 20);
    rows.into_iter()
        .enumerate()
        .map(|(i, (q, r))| {
            let q = index(&p, q).ok_or_else(|| Error::check(format!("row {i}: the query index is not a non-negative integer")))?;
            let refs = match ints_or_seq(&p, r)? {
                Some(Items::Ints(v)) => v,
                Some(Items::Objects(v)) => v
                    .iter()
                    .map(|&x| index(&p, x))
                    .collect::<Option<_>>()
                    .ok_or_else(|| Error::check(format!("row {i}: a reference index is not a non-negative integer")))?,
                None => vec![index(&p, r).ok_or_else(|| Error::check(format!("row {i}: references are neither a list nor an integer")))?],
            };
            budget = budget
                .checked_sub(refs.len())
                .ok_or_else(|| Error::check(format!("row {i}: more reference indices than a file of {} bytes can hold", bytes.len())))?;
            Ok((q, refs))
        })
        .collect()
}

/// `(descr, shape, data)` of a `.npy` file (format versions 1 to 3).
fn header(bytes: &[u8]) -> Result<(String, Vec<usize>, &[u8])> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(Error::check("not a .npy file (magic bytes missing)"));
    }
    let (len, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12),
        v => return Err(Error::check(format!(".npy format version {v} is not supported"))),
    };
    let text = bytes.get(start..start.saturating_add(len)).ok_or_else(|| Error::check(".npy header runs past the end of the file"))?;
    let text = std::str::from_utf8(text).map_err(|_| Error::check(".npy header is not text"))?;
    let field = |key: &str| -> Result<&str> {
        let at = text.find(&format!("'{key}'")).ok_or_else(|| Error::check(format!(".npy header has no {key:?}")))?;
        Ok(text[at + key.len() + 2..].trim_start().trim_start_matches(':').trim_start())
    };
    let descr = field("descr")?;
    let descr = descr.strip_prefix('\'').and_then(|d| d.split('\'').next()).ok_or_else(|| Error::check(".npy header: descr is not a string"))?;
    if field("fortran_order")?.starts_with("True") {
        return Err(Error::check("Fortran-ordered arrays are not supported"));
    }
    let shape = field("shape")?;
    let shape = shape.strip_prefix('(').and_then(|s| s.split(')').next()).ok_or_else(|| Error::check(".npy header: shape is not a tuple"))?;
    let shape = shape
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| Error::check(format!(".npy header: shape entry {s:?}"))))
        .collect::<Result<Vec<_>>>()?;
    Ok((descr.to_string(), shape, &bytes[start + len..]))
}

enum Items {
    /// Python objects (ids in the pickle).
    Objects(Vec<Id>),
    /// The values of a NumPy integer array.
    Ints(Vec<u64>),
}

fn is_reconstruct(func: &str) -> bool {
    matches!(func, "numpy.core.multiarray._reconstruct" | "numpy._core.multiarray._reconstruct")
}

/// A pickled NumPy array: its shape and items, or `None` if `id` is not one.
/// State layout (ndarray.__setstate__): (version, shape, dtype, fortran, data).
fn array(p: &Pickle, id: Id) -> Result<Option<(Vec<usize>, Items)>> {
    let Node::Call { func, state: Some(state), .. } = p.node(id) else { return Ok(None) };
    if !is_reconstruct(func) {
        return Ok(None);
    }
    let st = p.seq(*state).ok_or_else(|| Error::check("array state is not a tuple"))?;
    let [_, shape, dtype, fortran, data] = st else { return Err(Error::check(format!("array state has {} fields, expected 5", st.len()))) };
    let shape = p
        .seq(*shape)
        .ok_or_else(|| Error::check("array shape is not a tuple"))?
        .iter()
        .map(|&d| p.int(d).and_then(|d| usize::try_from(d).ok()))
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| Error::check("array shape holds a negative or non-integer size"))?;
    if p.int(*fortran) == Some(1) {
        return Err(Error::check("Fortran-ordered arrays are not supported"));
    }
    let count = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).ok_or_else(|| Error::check("array shape overflows"))?;
    let code = dtype_code(p, *dtype)?;
    let items = if code.get(1..).is_some_and(|c| c.starts_with('O')) {
        let v = p.seq(*data).ok_or_else(|| Error::check("object array data is not a list"))?.to_vec();
        Items::Objects(v)
    } else {
        let raw = bytes_of(p, *data).ok_or_else(|| Error::check("numeric array data is not bytes"))?;
        Items::Ints(int_values(&code, &raw)?)
    };
    let n = match &items {
        Items::Objects(v) => v.len(),
        Items::Ints(v) => v.len(),
    };
    if n != count {
        return Err(Error::check(format!("array of shape {shape:?} holds {n} items")));
    }
    Ok(Some((shape, items)))
}

/// The type code of a pickled `numpy.dtype(code, ...)` with its byte order from the state ("<i8").
fn dtype_code(p: &Pickle, id: Id) -> Result<String> {
    let Node::Call { func, args, state, .. } = p.node(id) else { return Err(Error::check("array dtype is not a numpy.dtype")) };
    if !func.ends_with(".dtype") {
        return Err(Error::check(format!("array dtype is {func}, not numpy.dtype")));
    }
    let code = args.first().and_then(|&a| p.str(a)).ok_or_else(|| Error::check("dtype without a type code"))?;
    let order = state.and_then(|s| p.seq(s)).and_then(|s| s.get(1).copied()).and_then(|o| p.str(o)).unwrap_or("|");
    Ok(format!("{}{code}", if order == ">" { ">" } else { "<" }))
}

/// Non-negative integers from a NumPy buffer of type `code` ("<i8", ">u4", ...).
fn int_values(code: &str, raw: &[u8]) -> Result<Vec<u64>> {
    let big = code.starts_with('>');
    let body = code.get(1..).unwrap_or("");
    let (kind, size) = body.split_at(body.char_indices().nth(1).map_or(body.len(), |(i, _)| i));
    let size: usize = size.parse().map_err(|_| Error::check(format!("dtype {code:?}")))?;
    if !matches!(kind, "i" | "u") || !matches!(size, 1 | 2 | 4 | 8) {
        return Err(Error::check(format!("dtype {code:?}: reference indices must be integers")));
    }
    if !raw.len().is_multiple_of(size) {
        return Err(Error::check(format!("{} bytes of {code:?} values", raw.len())));
    }
    raw.chunks_exact(size)
        .map(|c| {
            let mut b = [0u8; 8];
            if big {
                b[8 - size..].copy_from_slice(c);
                b.reverse();
            } else {
                b[..size].copy_from_slice(c);
            }
            if kind == "i" && c[if big { 0 } else { size - 1 }] & 0x80 != 0 {
                return Err(Error::check("a reference index is negative"));
            }
            Ok(u64::from_le_bytes(b))
        })
        .collect()
}

/// A list/tuple of objects, a NumPy array (of objects or integers), or `None` for anything else.
fn ints_or_seq(p: &Pickle, id: Id) -> Result<Option<Items>> {
    if let Some(s) = p.seq(id) {
        return Ok(Some(Items::Objects(s.to_vec())));
    }
    Ok(array(p, id)?.map(|(_, items)| items))
}

/// A non-negative integer: a Python int or a NumPy integer scalar
/// (`numpy.core.multiarray.scalar(dtype, bytes)`).
fn index(p: &Pickle, id: Id) -> Option<u64> {
    if let Some(v) = p.int(id) {
        return u64::try_from(v).ok();
    }
    let Node::Call { func, args, .. } = p.node(id) else { return None };
    if !func.ends_with("multiarray.scalar") {
        return None;
    }
    let code = dtype_code(p, *args.first()?).ok()?;
    let raw = bytes_of(p, *args.get(1)?)?;
    match int_values(&code, &raw).ok()?.as_slice() {
        [v] => Some(*v),
        _ => None,
    }
}

/// A bytes object: protocol 3+ writes it as bytes, protocol 2 as `_codecs.encode(text, "latin1")`.
fn bytes_of(p: &Pickle, id: Id) -> Option<Vec<u8>> {
    match p.node(id) {
        Node::Bytes(b) => Some(b.clone()),
        Node::Call { func, args, .. } if func == "_codecs.encode" && args.get(1).and_then(|&a| p.str(a)) == Some("latin1") => {
            p.str(*args.first()?)?.chars().map(|c| u8::try_from(c as u32).ok()).collect()
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn odd_dtype_codes_are_errors() {
        for code in ["<", "<\u{e9}8", "<i", "<i3", "<f8", ">u"] {
            assert!(int_values(code, &[0; 8]).is_err(), "{code:?}");
        }
        assert_eq!(int_values(">u2", &[1, 2]).unwrap(), vec![258]);
    }
}
