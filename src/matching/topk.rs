//! Streaming top-K: keeps the K best (score, index) pairs seen so far in a small sorted buffer, so
//! that scores against a whole map never need to be stored.

/// Best-first list of at most `k` entries; ties go to the lower index.
#[derive(Debug, Clone)]
pub struct TopK {
    k: usize,
    items: Vec<(f32, u32)>,
}

#[inline]
fn better(a: (f32, u32), b: (f32, u32)) -> bool {
    a.0 > b.0 || (a.0 == b.0 && a.1 < b.1)
}

impl TopK {
    pub fn new(k: usize) -> Self {
        TopK { k, items: Vec::with_capacity(k + 1) }
    }
    /// Offers one candidate; NaN scores are never kept.
    #[inline]
    pub fn push(&mut self, score: f32, index: u32) {
        if score.is_nan() || self.k == 0 {
            return;
        }
        if self.items.len() == self.k && !better((score, index), *self.items.last().unwrap()) {
            return;
        }
        let pos = self.items.partition_point(|&it| better(it, (score, index)));
        self.items.insert(pos, (score, index));
        self.items.truncate(self.k);
    }
    /// The kept (score, index) pairs, best first.
    pub fn items(&self) -> &[(f32, u32)] {
        &self.items
    }
    pub fn into_items(self) -> Vec<(f32, u32)> {
        self.items
    }
    /// Merges another top-K over a disjoint index range.
    pub fn merge(&mut self, other: &TopK) {
        for &(s, i) in other.items() {
            self.push(s, i);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Streaming keeps exactly the K best of a full sort (ties by lower index).
        #[test]
        fn equals_full_sort(scores in prop::collection::vec(0u8..20, 0..200), k in 1usize..15) {
            let mut t = TopK::new(k);
            for (i, &s) in scores.iter().enumerate() {
                t.push(s as f32, i as u32);
            }
            let mut all: Vec<(f32, u32)> = scores.iter().enumerate().map(|(i, &s)| (s as f32, i as u32)).collect();
            all.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            all.truncate(k);
            prop_assert_eq!(t.items(), &all[..]);
        }
    }
}
