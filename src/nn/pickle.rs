//! A minimal, safe pickle machine (Python's `pickle` protocols 2-5, the opcodes that PyTorch
//! state dicts and NumPy object arrays use), so that `.pt` weights and VPR-Bench's
//! `ground_truth_new.npy` can be read without Python.
//!
//! Objects live in an arena and the stack holds indices, so a memoised object that is mutated
//! later (a list filled by APPENDS after BINPUT) is seen the same through every reference, as in
//! Python, and a malicious pickle cannot blow up memory by re-reading the memo: every opcode adds
//! at most one node, so the arena is bounded by the input length; what an opcode copies (call
//! arguments, joined global names) is charged to a budget proportional to the input, so a short
//! pickle cannot make quadratic copies either. Calls (REDUCE, NEWOBJ) are
//! never executed: they become `Node::Call` nodes that the reader interprets.

use crate::error::{Error, Result};
use std::collections::HashMap;

/// Index of a node in the arena.
pub type Id = usize;

#[derive(Debug, Clone, PartialEq)]
pub enum Node {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<Id>),
    Tuple(Vec<Id>),
    Dict(Vec<(Id, Id)>),
    /// `module.name`
    Global(String),
    /// A call of `func` (a global) with `args`, with the state BUILD gave it and the items
    /// SETITEM(S)/APPEND(S) added to the resulting object.
    Call {
        func: String,
        args: Vec<Id>,
        state: Option<Id>,
        items: Vec<(Id, Id)>,
        appended: Vec<Id>,
    },
    /// A persistent id (PyTorch's storage references).
    Persistent(Id),
}

/// A loaded pickle: the arena and the id of the value it returned.
#[derive(Debug, Clone)]
pub struct Pickle {
    nodes: Vec<Node>,
    pub root: Id,
}

enum Slot {
    Node(Id),
    Mark,
}

impl Pickle {
    pub fn node(&self, id: Id) -> &Node {
        &self.nodes[id]
    }
    pub fn int(&self, id: Id) -> Option<i64> {
        match self.node(id) {
            Node::Int(v) => Some(*v),
            Node::Bool(b) => Some(*b as i64),
            _ => None,
        }
    }
    pub fn str(&self, id: Id) -> Option<&str> {
        match self.node(id) {
            Node::Str(s) => Some(s),
            _ => None,
        }
    }
    /// Items of a list or tuple.
    pub fn seq(&self, id: Id) -> Option<&[Id]> {
        match self.node(id) {
            Node::List(v) | Node::Tuple(v) => Some(v),
            _ => None,
        }
    }
    /// Key-value pairs of a dict, or of an object filled by SETITEMS (an OrderedDict).
    pub fn pairs(&self, id: Id) -> Option<&[(Id, Id)]> {
        match self.node(id) {
            Node::Dict(v) => Some(v),
            Node::Call { items, .. } => Some(items),
            _ => None,
        }
    }

    /// Runs the pickle program in `data`; what it cannot run is an [`Error::Check`] (the caller
    /// names the file).
    pub fn load(data: &[u8]) -> Result<Pickle> {
        Ok(Pickle::load_prefix(data)?.0)
    }

    /// [`Pickle::load`] of the pickle at the start of `data`, with the bytes it took (up to and
    /// including its STOP): what a file of several pickles one after another is read with.
    pub fn load_prefix(data: &[u8]) -> Result<(Pickle, usize)> {
        let budget = data.len().saturating_mul(COPY_BUDGET_PER_BYTE).saturating_add(4096);
        Machine { data, pos: 0, nodes: Vec::new(), stack: Vec::new(), memo: HashMap::new(), budget }.run()
    }
}

/// Items or bytes an opcode may copy, in all, per byte of input.
const COPY_BUDGET_PER_BYTE: usize = 16;

struct Machine<'a> {
    data: &'a [u8],
    pos: usize,
    nodes: Vec<Node>,
    stack: Vec<Slot>,
    memo: HashMap<u32, Id>,
    /// What copies may still cost (items or bytes).
    budget: usize,
}

impl<'a> Machine<'a> {
    fn spend(&mut self, n: usize) -> Result<()> {
        self.budget = self.budget.checked_sub(n).ok_or_else(|| Error::check("the pickle copies more data than its size allows"))?;
        Ok(())
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.data.len()).ok_or_else(|| Error::check("pickle ends early"))?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> Result<u32> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self) -> Result<u64> {
        let b = self.take(8)?;
        Ok(u64::from_le_bytes(b.try_into().map_err(|_| Error::check("pickle ends early"))?))
    }
    fn line(&mut self) -> Result<&'a str> {
        let rest = &self.data[self.pos..];
        let n = rest.iter().position(|&b| b == b'\n').ok_or_else(|| Error::check("text argument without newline"))?;
        let s = std::str::from_utf8(&rest[..n]).map_err(|_| Error::check("text argument is not UTF-8"))?;
        self.pos += n + 1;
        Ok(s)
    }
    fn len_arg(&mut self, n: u64) -> Result<usize> {
        usize::try_from(n)
            .ok()
            .filter(|&n| n <= self.data.len() - self.pos)
            .ok_or_else(|| Error::check(format!("length {n} runs past the end of the pickle")))
    }
    fn push(&mut self, n: Node) -> Id {
        self.nodes.push(n);
        let id = self.nodes.len() - 1;
        self.stack.push(Slot::Node(id));
        id
    }
    fn pop(&mut self, what: &str) -> Result<Id> {
        match self.stack.pop() {
            Some(Slot::Node(id)) => Ok(id),
            Some(Slot::Mark) => Err(Error::check(format!("{what}: found a MARK"))),
            None => Err(Error::check(format!("{what}: stack is empty"))),
        }
    }
    fn top(&self, what: &str) -> Result<Id> {
        match self.stack.last() {
            Some(Slot::Node(id)) => Ok(*id),
            _ => Err(Error::check(format!("{what}: no object on the stack"))),
        }
    }
    fn pop_mark(&mut self) -> Result<Vec<Id>> {
        let m = self.stack.iter().rposition(|s| matches!(s, Slot::Mark)).ok_or_else(|| Error::check("MARK missing"))?;
        // `m` is the last mark, so everything above it is a node
        let items = self.stack.split_off(m + 1).into_iter().filter_map(|s| if let Slot::Node(id) = s { Some(id) } else { None }).collect();
        self.stack.pop();
        Ok(items)
    }
    fn memoise(&mut self, key: u32) -> Result<()> {
        let id = self.top("memo")?;
        self.memo.insert(key, id);
        Ok(())
    }
    fn recall(&mut self, key: u32) -> Result<()> {
        let id = *self.memo.get(&key).ok_or_else(|| Error::check(format!("memo {key} was never stored")))?;
        self.stack.push(Slot::Node(id));
        Ok(())
    }
    fn global(&mut self, id: Id) -> Result<String> {
        let Node::Global(g) = &self.nodes[id] else { return Err(Error::check("call of something that is not a global")) };
        let g = g.clone();
        self.spend(g.len())?;
        Ok(g)
    }
    fn set_items(&mut self, target: Id, kv: Vec<(Id, Id)>) -> Result<()> {
        match &mut self.nodes[target] {
            Node::Dict(d) => d.extend(kv),
            Node::Call { items, .. } => items.extend(kv),
            _ => return Err(Error::check("SETITEM on an object that is not a dict")),
        }
        Ok(())
    }
    fn append(&mut self, target: Id, values: Vec<Id>) -> Result<()> {
        match &mut self.nodes[target] {
            Node::List(l) => l.extend(values),
            Node::Call { appended, .. } => appended.extend(values),
            _ => return Err(Error::check("APPEND on an object that is not a list")),
        }
        Ok(())
    }

    fn run(mut self) -> Result<(Pickle, usize)> {
        loop {
            let op = self.u8()?;
            match op {
                0x80 => {
                    self.u8()?; // PROTO
                }
                0x95 => {
                    self.u64()?; // FRAME: a length hint
                }
                b'.' => break,
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.push(Node::Global(format!("{module}.{name}")));
                }
                0x93 => {
                    // STACK_GLOBAL
                    let name = self.pop("STACK_GLOBAL")?;
                    let module = self.pop("STACK_GLOBAL")?;
                    let (Node::Str(m), Node::Str(n)) = (&self.nodes[module], &self.nodes[name]) else {
                        return Err(Error::check("STACK_GLOBAL of non-strings"));
                    };
                    let g = format!("{m}.{n}");
                    self.spend(g.len())?;
                    self.push(Node::Global(g));
                }
                b'p' => {
                    let key = self.line()?.parse::<u32>().map_err(|_| Error::check("PUT with a bad key"))?;
                    self.memoise(key)?;
                }
                b'q' => {
                    let key = self.u8()? as u32;
                    self.memoise(key)?;
                }
                b'r' => {
                    let key = self.u32()?;
                    self.memoise(key)?;
                }
                0x94 => {
                    let key = u32::try_from(self.memo.len()).map_err(|_| Error::check("memo overflow"))?;
                    self.memoise(key)?; // MEMOIZE
                }
                b'g' => {
                    let key = self.line()?.parse::<u32>().map_err(|_| Error::check("GET with a bad key"))?;
                    self.recall(key)?;
                }
                b'h' => {
                    let key = self.u8()? as u32;
                    self.recall(key)?;
                }
                b'j' => {
                    let key = self.u32()?;
                    self.recall(key)?;
                }
                b')' => {
                    self.push(Node::Tuple(vec![]));
                }
                b']' => {
                    self.push(Node::List(vec![]));
                }
                b'}' => {
                    self.push(Node::Dict(vec![]));
                }
                b'(' => self.stack.push(Slot::Mark),
                b'N' => {
                    self.push(Node::None);
                }
                0x88 | 0x89 => {
                    self.push(Node::Bool(op == 0x88));
                }
                b'K' => {
                    let v = self.u8()? as i64;
                    self.push(Node::Int(v));
                }
                b'M' => {
                    let b = self.take(2)?;
                    self.push(Node::Int(u16::from_le_bytes([b[0], b[1]]) as i64));
                }
                b'J' => {
                    let v = self.u32()? as i32 as i64;
                    self.push(Node::Int(v));
                }
                b'I' => {
                    let t = self.line()?;
                    let v = match t {
                        "00" => Node::Bool(false),
                        "01" => Node::Bool(true),
                        _ => Node::Int(t.parse().map_err(|_| Error::check(format!("INT {t:?}")))?),
                    };
                    self.push(v);
                }
                0x8a | 0x8b => {
                    // LONG1 / LONG4: little-endian two's complement
                    let n = if op == 0x8a { self.u8()? as u64 } else { self.u32()? as u64 };
                    let n = self.len_arg(n)?;
                    if n > 8 {
                        return Err(Error::check(format!("integer of {n} bytes does not fit 64 bits")));
                    }
                    let b = self.take(n)?;
                    let mut v: i64 = 0;
                    for (k, &byte) in b.iter().enumerate() {
                        v |= (byte as i64) << (8 * k);
                    }
                    if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                        v -= 1i64 << (8 * n);
                    }
                    self.push(Node::Int(v));
                }
                b'G' => {
                    let b = self.take(8)?;
                    let v = f64::from_be_bytes(b.try_into().map_err(|_| Error::check("BINFLOAT"))?);
                    self.push(Node::Float(v));
                }
                b'X' | 0x8c | 0x8d => {
                    let n = match op {
                        b'X' => self.u32()? as u64,
                        0x8c => self.u8()? as u64,
                        _ => self.u64()?,
                    };
                    let n = self.len_arg(n)?;
                    let s = std::str::from_utf8(self.take(n)?).map_err(|_| Error::check("string is not UTF-8"))?.to_string();
                    self.push(Node::Str(s));
                }
                b'B' | b'C' | 0x8e | b'T' | b'U' => {
                    let n = match op {
                        b'B' | b'T' => self.u32()? as u64,
                        b'C' | b'U' => self.u8()? as u64,
                        _ => self.u64()?,
                    };
                    let n = self.len_arg(n)?;
                    let b = self.take(n)?.to_vec();
                    self.push(Node::Bytes(b));
                }
                b't' => {
                    let items = self.pop_mark()?;
                    self.push(Node::Tuple(items));
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    let mut items = Vec::with_capacity(n);
                    for _ in 0..n {
                        items.push(self.pop("TUPLEn")?);
                    }
                    items.reverse();
                    self.push(Node::Tuple(items));
                }
                b'l' => {
                    let items = self.pop_mark()?;
                    self.push(Node::List(items));
                }
                b'd' => {
                    let items = self.pop_mark()?;
                    if items.len() % 2 != 0 {
                        return Err(Error::check("DICT with an odd number of items"));
                    }
                    let kv = items.chunks(2).map(|c| (c[0], c[1])).collect();
                    self.push(Node::Dict(kv));
                }
                b'a' => {
                    let v = self.pop("APPEND")?;
                    let target = self.top("APPEND")?;
                    self.append(target, vec![v])?;
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    let target = self.top("APPENDS")?;
                    self.append(target, items)?;
                }
                b's' => {
                    let v = self.pop("SETITEM")?;
                    let k = self.pop("SETITEM")?;
                    let target = self.top("SETITEM")?;
                    self.set_items(target, vec![(k, v)])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    if items.len() % 2 != 0 {
                        return Err(Error::check("SETITEMS with an odd number of items"));
                    }
                    let target = self.top("SETITEMS")?;
                    self.set_items(target, items.chunks(2).map(|c| (c[0], c[1])).collect())?;
                }
                b'R' | 0x81 => {
                    // REDUCE (callable, args) / NEWOBJ (class, args)
                    let args = self.pop("REDUCE")?;
                    let f = self.pop("REDUCE")?;
                    let func = self.global(f)?;
                    let args = match &self.nodes[args] {
                        Node::Tuple(a) => a.clone(),
                        _ => return Err(Error::check("REDUCE arguments are not a tuple")),
                    };
                    self.spend(args.len())?;
                    self.push(Node::Call { func, args, state: None, items: vec![], appended: vec![] });
                }
                b'b' => {
                    let state = self.pop("BUILD")?;
                    let target = self.top("BUILD")?;
                    // BUILD on a plain value: state is ignored (Python would set attributes)
                    if let Node::Call { state: s, .. } = &mut self.nodes[target] {
                        *s = Some(state);
                    }
                }
                b'Q' => {
                    let pid = self.pop("BINPERSID")?;
                    self.push(Node::Persistent(pid));
                }
                b'0' => {
                    self.stack.pop().ok_or_else(|| Error::check("POP on an empty stack"))?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let id = self.top("DUP")?;
                    self.stack.push(Slot::Node(id));
                }
                other => return Err(Error::check(format!("unsupported pickle opcode 0x{other:02x} at byte {}", self.pos - 1))),
            }
        }
        let root = self.pop("STOP")?;
        Ok((Pickle { nodes: self.nodes, root }, self.pos))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `pickle.dumps([1, -2, 300, 2**40, "x", (None, True)], protocol=2)`, then `protocol=4`.
    const LIST_P2: &[u8] = b"\x80\x02]q\x00(K\x01J\xfe\xff\xff\xffM,\x01\x8a\x06\x00\x00\x00\x00\x00\x01X\x01\x00\x00\x00xq\x01N\x88\x86q\x02e.";
    const LIST_P4: &[u8] =
        b"\x80\x04\x95\x1f\x00\x00\x00\x00\x00\x00\x00]\x94(K\x01J\xfe\xff\xff\xffM,\x01\x8a\x06\x00\x00\x00\x00\x00\x01\x8c\x01x\x94N\x88\x86\x94e.";

    #[test]
    fn reads_lists_ints_strings_and_tuples_in_protocols_2_and_4() {
        for data in [LIST_P2, LIST_P4] {
            let p = Pickle::load(data).unwrap();
            let items = p.seq(p.root).unwrap();
            let ints: Vec<Option<i64>> = items[..4].iter().map(|&i| p.int(i)).collect();
            assert_eq!(ints, vec![Some(1), Some(-2), Some(300), Some(1 << 40)]);
            assert_eq!(p.str(items[4]), Some("x"));
            let t = p.seq(items[5]).unwrap();
            assert_eq!((p.node(t[0]), p.node(t[1])), (&Node::None, &Node::Bool(true)));
        }
    }

    #[test]
    fn a_memoised_list_filled_later_is_the_same_object() {
        // l = [7]; pickle.dumps([l, l], protocol=2): the inner list is memoised empty, filled by
        // APPEND, then referenced again by BINGET
        let data = b"\x80\x02]q\x00(]q\x01K\x07ah\x01e.";
        let p = Pickle::load(data).unwrap();
        let outer = p.seq(p.root).unwrap();
        assert_eq!(outer.len(), 2);
        assert_eq!(outer[0], outer[1]);
        assert_eq!(p.seq(outer[1]).unwrap().len(), 1);
    }

    #[test]
    fn truncated_or_hostile_input_is_an_error_not_a_panic() {
        for cut in 0..LIST_P4.len() {
            assert!(Pickle::load(&LIST_P4[..cut]).is_err(), "cut at {cut}");
        }
        for bad in [&b"\x80\x02h\x05."[..], b"X\xff\xff\xff\xffabc", b"\x8b\xff\xff\xff\xff", b"(t\x8a\x09123456789.", b"R.", b"e."] {
            assert!(Pickle::load(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn repeated_calls_on_one_large_tuple_run_out_of_budget_not_memory() {
        // f = a global, t = a tuple of 20000 ints, both memoised; then f(*t) 20000 times: each call
        // would copy the tuple, 400M ids from a 140 kB pickle
        let mut p = b"\x80\x02cm\nf\nq\x00(".to_vec();
        p.extend(std::iter::repeat_n(&b"K\x01"[..], 20_000).flatten());
        p.extend_from_slice(b"tq\x01");
        p.extend(std::iter::repeat_n(&b"h\x00h\x01R0"[..], 20_000).flatten());
        p.push(b'.');
        let err = Pickle::load(&p).unwrap_err();
        assert!(err.to_string().contains("copies more"), "{err}");
    }
}
