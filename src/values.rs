//! Borrowed arrays of stored real values: `f32`, or `f16` (IEEE half precision, kept as its bits)
//! that is widened to `f32` as it is read. Maps may store global descriptors and appearance vectors
//! in f16 to halve their size; every computation stays in f32 (a stored f16 value widens exactly).

use half::slice::{HalfBitsSliceExt, HalfFloatSliceExt};
use serde::{Deserialize, Serialize};

/// How a map stores its global descriptors and appearance vectors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ValueType {
    /// 4 bytes per value: the encoder's values bit for bit.
    #[default]
    F32,
    /// 2 bytes per value, rounded to nearest (relative error below 2^-11 in the normal range).
    F16,
}

impl ValueType {
    pub fn bytes(self) -> usize {
        match self {
            ValueType::F32 => 4,
            ValueType::F16 => 2,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            ValueType::F32 => "f32",
            ValueType::F16 => "f16",
        }
    }
}

/// Largest finite f16 value: stored values beyond it would become infinite.
pub const F16_MAX: f32 = 65504.0;

/// A borrowed run of values of either storage type.
#[derive(Debug, Clone, Copy)]
pub enum Values<'a> {
    F32(&'a [f32]),
    /// f16 bit patterns.
    F16(&'a [u16]),
}

impl<'a> Values<'a> {
    pub const EMPTY: Values<'static> = Values::F32(&[]);

    pub fn len(&self) -> usize {
        match self {
            Values::F32(v) => v.len(),
            Values::F16(v) => v.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Values `a..b` (panics outside the run, like a slice).
    pub fn slice(&self, a: usize, b: usize) -> Values<'a> {
        match self {
            Values::F32(v) => Values::F32(&v[a..b]),
            Values::F16(v) => Values::F16(&v[a..b]),
        }
    }
    /// The f32 slice itself when the values are stored as f32.
    pub fn as_f32(&self) -> Option<&'a [f32]> {
        match self {
            Values::F32(v) => Some(v),
            Values::F16(_) => None,
        }
    }
    /// Widens the values into `dst` (of the same length).
    pub fn write_to(&self, dst: &mut [f32]) {
        match self {
            Values::F32(v) => dst.copy_from_slice(v),
            Values::F16(v) => v.reinterpret_cast::<half::f16>().convert_to_f32_slice(dst),
        }
    }
    /// Appends the values, widened, to `out`.
    pub fn extend_into(&self, out: &mut Vec<f32>) {
        let at = out.len();
        out.resize(at + self.len(), 0.0);
        self.write_to(&mut out[at..]);
    }
    pub fn to_vec(&self) -> Vec<f32> {
        let mut v = Vec::with_capacity(self.len());
        self.extend_into(&mut v);
        v
    }
    /// The first value (index and value, widened) for which `pred` holds.
    pub fn position(&self, pred: impl Fn(f32) -> bool) -> Option<(usize, f32)> {
        match self {
            Values::F32(v) => v.iter().copied().enumerate().find(|&(_, x)| pred(x)),
            Values::F16(v) => v.iter().map(|&b| half::f16::from_bits(b).to_f32()).enumerate().find(|&(_, x)| pred(x)),
        }
    }
    /// The values as an f32 slice: borrowed when stored as f32, else widened into `buf`.
    pub fn widened<'s>(&self, buf: &'s mut Vec<f32>) -> &'s [f32]
    where
        'a: 's,
    {
        match *self {
            Values::F32(v) => v,
            Values::F16(v) => {
                buf.clear();
                buf.resize(v.len(), 0.0);
                v.reinterpret_cast::<half::f16>().convert_to_f32_slice(buf);
                buf
            }
        }
    }
    /// Sum of products with `other`, in order, accumulated in f32: exactly
    /// `a.iter().zip(b).map(|(x, y)| x * y).sum()` over the widened values (f16 runs are widened
    /// a block at a time with the processor's conversion instructions, not value by value).
    pub fn dot(&self, other: &Values) -> f32 {
        if let (Values::F32(a), Values::F32(b)) = (self, other) {
            return a.iter().zip(*b).map(|(x, y)| x * y).sum();
        }
        const BLOCK: usize = 256;
        let n = self.len().min(other.len());
        let (mut x, mut y) = ([0.0f32; BLOCK], [0.0f32; BLOCK]);
        // the neutral element `sum` starts from, so that the fold below gives the same bits
        let mut acc: f32 = std::iter::empty::<f32>().sum();
        for a in (0..n).step_by(BLOCK) {
            let b = (a + BLOCK).min(n);
            self.slice(a, b).write_to(&mut x[..b - a]);
            other.slice(a, b).write_to(&mut y[..b - a]);
            acc = x[..b - a].iter().zip(&y[..b - a]).fold(acc, |s, (p, q)| s + p * q);
        }
        acc
    }
}

/// f32 values as f16 bit patterns (round to nearest even).
pub fn to_f16_bits(src: &[f32]) -> Vec<u16> {
    let mut out = vec![half::f16::ZERO; src.len()];
    out.convert_from_f32_slice(src);
    out.reinterpret_cast().to_vec()
}

/// Each value rounded through f16 and back: what an f16 map returns for `v`.
pub fn round_through_f16(v: &mut [f32]) {
    let bits = to_f16_bits(v);
    Values::F16(&bits).write_to(v);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f16_round_trip_and_dot() {
        let x = [0.0f32, 1.0, 0.5, 0.333_333_34, -0.25, 1e-3];
        let bits = to_f16_bits(&x);
        let back = Values::F16(&bits).to_vec();
        for (a, b) in x.iter().zip(&back) {
            assert!((a - b).abs() <= a.abs() * 1e-3 + 1e-7, "{a} -> {b}");
        }
        // widening is exact, so narrowing again gives the same bits
        assert_eq!(to_f16_bits(&back), bits);
        let f = Values::F32(&x);
        assert_eq!(f.dot(&f), x.iter().map(|v| v * v).sum::<f32>());
        assert_eq!(Values::F16(&bits).dot(&f), back.iter().zip(&x).map(|(a, b)| a * b).sum::<f32>());
        assert_eq!(Values::F16(&bits).slice(1, 3).to_vec(), vec![1.0, 0.5]);
        // longer than one conversion block, f16 on either side or both: the widened f32 dot, bit for bit
        let long: Vec<f32> = (0..1000).map(|i| ((i * 37 % 101) as f32 - 50.0) / 64.0).collect();
        let lb = to_f16_bits(&long);
        let wide = Values::F16(&lb).to_vec();
        let reference = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
        assert_eq!(Values::F16(&lb).dot(&Values::F32(&long)).to_bits(), reference(&wide, &long).to_bits());
        assert_eq!(Values::F32(&long).dot(&Values::F16(&lb)).to_bits(), reference(&long, &wide).to_bits());
        assert_eq!(Values::F16(&lb).dot(&Values::F16(&lb)).to_bits(), reference(&wide, &wide).to_bits());
        let mut buf = Vec::new();
        assert_eq!(Values::F16(&lb).widened(&mut buf), &wide[..]);
        assert_eq!(Values::F32(&long).widened(&mut buf).as_ptr(), long.as_ptr(), "f32 values are borrowed");
    }
}
