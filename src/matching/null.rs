//! The explicit null of the verified score's evidence (issue 60): what verification finds between
//! references that look alike to the coarse stage but are other places, and, for the compact
//! HOGs, what the same place looks like beside it (sweep 22).
//!
//! A query's wrong candidates are its look-alikes: in a corridor of repeated doors, floors of
//! one layout or a railway in snow they show inliers and HOG similarity however wrong they are.
//! Scoring a candidate's evidence against the query's own other candidates (the `unusual`
//! z-score of issue 51) is not a test: where the candidates' counts are alike, chance
//! differences become large z-scores, and the score picked noise exactly where geometry says
//! least (an indoor corridor at 160x120: `verified` 0.532 against its coarse stage's 0.847).
//!
//! Here the null is measured, per map, the way an empirical null is in multiple testing (Efron,
//! "Large-scale simultaneous hypothesis testing: the choice of a null hypothesis", JASA 2004):
//! `null_sources` references evenly spaced along the map are matched against the map by the
//! coarse stage of `verified`; of each one's candidates, those that cannot be the same place
//! (further than `null_gap` positions along its traversal) stand for a query's wrong candidates
//! and are verified. Their inliers and compact-HOG cosines are the null sample. A candidate's
//! inliers count by their tail probability under that sample, the query's K candidates in the
//! multiple-testing count (the expected number of false alarms of an a-contrario test, Desolneux,
//! Moisan & Morel 2000; Moisan & Stival 2004): NFA = K x P(null >= observed). Beyond the
//! sample's range the tail is extrapolated (peaks over threshold, Pickands 1975): an exponential
//! fit to the top tenth of ln(1 + inliers) (a Pareto tail of the counts) and of the cosines.
//!
//! The compact HOGs (maps of small frames) count by a likelihood ratio instead (sweep 22): how
//! much more often the map's own same-place pairs (each source with its neighbours one position
//! away along its traversal) reach a candidate's cosine than its look-alikes do,
//! P(near >= c) / P(null >= c) (Neyman & Pearson 1933: the most powerful test of "this place" against
//! "a look-alike", both measured on the map). Where HOG tells the map's places apart (a railway in
//! snow at 64x32) the ratio of a right candidate is in the hundreds; where it does not (landmarks
//! seen from other viewpoints, floors of one layout; an unordered collection whose neighbours are
//! other places) the same-place pairs are no more alike than the look-alikes (in their top tenth
//! at most a little more), the ratio stays within a few times 1, below the
//! `verification.compact_hog_above` decades the term needs, and the term is silent however alike a
//! candidate looks. A test against the look-alikes alone could not tell those maps apart: it
//! spoke on both.
//!
//! The measurement depends on the references and on the config that makes candidates and
//! verifies them (never on the score's weights): [`key`] names it. `map build` measures it under
//! the build's config and stores it in the manifest ([`StoredNull`]; `map add` and `map remove`
//! measure it again once the map has doubled or halved): then every process and every shard of
//! the map tests against that one. Elsewhere (another config, a map built without one, sources
//! in memory) it is measured on a source's first use and kept for the process ([`kept_or`],
//! measured by `matching::measure_null`); the same references under the same config give the
//! same null, and a stored map keeps it across its generations until it has doubled or halved
//! (a loop-closure stream commits every few frames and would otherwise measure it at every
//! commit).

use crate::config::{Config, VerificationConfig};
pub use crate::descriptors::null::{NullEvidence, StoredNull, MIN_NULL_PAIRS};
use crate::descriptors::source::{Place, RefSource, SourceKey};
use crate::error::Result;
use std::sync::{Arc, Mutex};

/// Share of the null sample the tail model is fitted to (its top tenth).
const TAIL_SHARE: f64 = 0.1;
/// Least number of exceedances a tail is fitted to.
const TAIL_MIN: usize = 10;
/// Smallest scale of the fitted tails: a sample whose top tenth is all one value does not make
/// every larger one infinitely significant.
const TAIL_SCALE_FLOOR: f64 = 0.05;
/// Tail probabilities of one null sample: the empirical survival function, with an
/// exponential tail fitted above the threshold.
struct Tail<'a> {
    sorted: &'a [f64],
    threshold: f64,
    at_threshold: f64,
    scale: f64,
}

impl<'a> Tail<'a> {
    /// `sorted` ascending; `None` for a sample too small to test against.
    fn fit(sorted: &'a [f64]) -> Option<Tail<'a>> {
        let n = sorted.len();
        if n < MIN_NULL_PAIRS {
            return None;
        }
        let m = ((n as f64 * TAIL_SHARE).ceil() as usize).max(TAIL_MIN).min(n);
        let threshold = sorted[n - m];
        let scale = (sorted[n - m..].iter().map(|x| x - threshold).sum::<f64>() / m as f64).max(TAIL_SCALE_FLOOR);
        let at_threshold = Self::empirical(sorted, threshold);
        Some(Tail { sorted, threshold, at_threshold, scale })
    }
    /// (1 + #{x >= v}) / (n + 1): never 0, as a sample of n cannot show less.
    fn empirical(sorted: &[f64], v: f64) -> f64 {
        let at_least = sorted.len() - sorted.partition_point(|&x| x < v);
        (1 + at_least) as f64 / (sorted.len() + 1) as f64
    }
    /// P(null >= v).
    fn p(&self, v: f64) -> f64 {
        match v > self.threshold {
            false => Self::empirical(self.sorted, v),
            true => self.at_threshold * (-(v - self.threshold) / self.scale).exp(),
        }
    }
}

impl NullEvidence {
    /// ln(1 + inliers) of every null pair, ascending.
    fn log_inliers(&self) -> Vec<f64> {
        self.inliers.iter().enumerate().flat_map(|(k, &c)| std::iter::repeat_n((k as f64).ln_1p(), c as usize)).collect()
    }
    /// P(a null pair shows at least `k` inliers); 1 where the sample is too small to say.
    pub fn p_inliers(&self, k: u32) -> f64 {
        let sorted = self.log_inliers();
        Tail::fit(&sorted).map_or(1.0, |t| t.p((k as f64).ln_1p()))
    }
    /// The compact HOGs' likelihood ratio at cosine `c`: P(a same-place pair is at least `c`
    /// alike) / P(a null pair is), each the survival function of its sample with the same
    /// exponential tail fitted above its top tenth (so that beyond the largest same-place cosine
    /// the ratio does not grow by the null's tail alone); 1 (no evidence) where either sample is
    /// too small to say.
    pub fn compact_hog_ratio(&self, c: f32) -> f64 {
        let (null, near) = self.compact_hog_samples();
        Self::ratio(Tail::fit(&null).as_ref(), Tail::fit(&near).as_ref(), c)
    }
    /// The compact HOGs' null and same-place samples as f64, ascending.
    fn compact_hog_samples(&self) -> (Vec<f64>, Vec<f64>) {
        let f = |v: &[f32]| v.iter().map(|&x| x as f64).collect();
        (f(&self.compact_hog), f(&self.compact_hog_near))
    }
    fn ratio(null: Option<&Tail>, near: Option<&Tail>, c: f32) -> f64 {
        match (null, near) {
            (Some(null), Some(near)) => near.p(c as f64) / null.p(c as f64),
            _ => 1.0,
        }
    }
    /// The inliers' tail probabilities and the compact HOGs' likelihood ratios of many pairs at
    /// once (the samples sorted once).
    pub fn tail_and_ratio(&self, inliers: &[Option<u32>], hog: &[Option<f32>]) -> (Vec<Option<f32>>, Vec<Option<f32>>) {
        let li = self.log_inliers();
        let ti = Tail::fit(&li);
        let (null, near) = self.compact_hog_samples();
        let (th, tn) = (Tail::fit(&null), Tail::fit(&near));
        let pi = inliers.iter().map(|k| k.map(|k| ti.as_ref().map_or(1.0, |t| t.p((k as f64).ln_1p())) as f32)).collect();
        let rh = hog.iter().map(|c| c.map(|c| Self::ratio(th.as_ref(), tn.as_ref(), c) as f32)).collect();
        (pi, rh)
    }
    /// Inlier count at quantile `q` of the sample (for `map info`).
    pub fn inliers_quantile(&self, q: f64) -> u32 {
        let total: u64 = self.inliers.iter().map(|&c| c as u64).sum();
        let want = (q * total as f64).ceil() as u64;
        let mut seen = 0;
        for (k, &c) in self.inliers.iter().enumerate() {
            seen += c as u64;
            if seen >= want.max(1) {
                return k as u32;
            }
        }
        0
    }
}

/// What a null's sample holds, in its key: the look-alikes' inliers and compact-HOG cosines, and
/// the same-place pairs' cosines (sweep 22).
const MEASURED_SAMPLES: &str = "null pairs: inliers, compact hog; near pairs: compact hog";

/// What a null is measured under: the config that makes `verified`'s candidates and verifies
/// them, and the null's own parameters (none of the score's weights), as a SHA-256.
pub fn key(cfg: &Config) -> String {
    let v = measurement(&cfg.verification);
    // the SHA-256 of those sections' JSON: compact in a manifest, and no config text there
    // MEASURED_SAMPLES names what is measured: a null of an older release (without its same-place
    // sample) is measured again rather than read as one that has none
    crate::util::sha256_hex(serde_json::json!([MEASURED_SAMPLES, cfg.matching, cfg.global, cfg.index, cfg.classes, v]).to_string().as_bytes())
}

/// `v` with the verified score's weights at their defaults: what a measurement depends on.
pub fn measurement(v: &VerificationConfig) -> VerificationConfig {
    let d = VerificationConfig::default();
    let mut m = v.clone();
    (
        m.w_inliers,
        m.w_coarse,
        m.w_fine,
        m.inliers,
        m.unusual_above,
        m.min_inliers,
        m.w_compact_hog,
        m.compact_hog_above,
        m.null_alarms,
        m.max_bonus,
    ) = (
        d.w_inliers,
        d.w_coarse,
        d.w_fine,
        d.inliers,
        d.unusual_above,
        d.min_inliers,
        d.w_compact_hog,
        d.compact_hog_above,
        d.null_alarms,
        d.max_bonus,
    );
    // w_glue's weight alone: whether LighterGlue runs (w_glue > 0) is a measurement
    if m.w_glue > 0.0 {
        m.w_glue = 1.0;
    }
    m
}

/// The sources of a map of `n` references: `count` evenly spaced.
pub fn sources(n: usize, count: usize) -> Vec<usize> {
    let s = count.min(n);
    let mut v: Vec<usize> = (0..s).map(|i| i * n / s.max(1)).collect();
    v.dedup();
    v
}

/// The null pairs of candidate lists (`lists[i]` those of reference `sources[i]`): per source
/// its candidates (best first) that are not within `gap` positions of it along the same
/// traversal, at most `k` of them.
pub fn null_pairs(refs: &dyn RefSource, sources: &[usize], lists: &[Vec<(f32, u32)>], gap: u32, k: usize) -> Vec<(u32, u32)> {
    pairs_apart(&|i| refs.place(i), sources, lists, gap, k)
}

/// The same-place pairs of `sources` (indices into `sources`, references): each source with the
/// references one position before and after it along its traversal, where the map holds them.
pub fn near_pairs(refs: &dyn RefSource, sources: &[usize]) -> Vec<(u32, u32)> {
    pairs_beside(&|i| refs.place(i), &|p| refs.at(p), sources)
}

/// [`near_pairs`] with the references' places given by `place` and the reference at a place by `at`.
fn pairs_beside(place: &dyn Fn(usize) -> Place, at: &dyn Fn(Place) -> Option<usize>, sources: &[usize]) -> Vec<(u32, u32)> {
    let mut out = Vec::new();
    for (i, &s) in sources.iter().enumerate() {
        let p = place(s);
        let before = p.position.checked_sub(1).map(|position| Place { position, ..p });
        let after = p.position.checked_add(1).map(|position| Place { position, ..p });
        out.extend([before, after].into_iter().flatten().filter_map(at).filter(|&r| r != s).map(|r| (i as u32, r as u32)));
    }
    out
}

/// [`null_pairs`] with the references' places given by `place`.
fn pairs_apart(place: &dyn Fn(usize) -> Place, sources: &[usize], lists: &[Vec<(f32, u32)>], gap: u32, k: usize) -> Vec<(u32, u32)> {
    let mut out = Vec::new();
    for (i, (&s, list)) in sources.iter().zip(lists).enumerate() {
        let a = place(s);
        let other = |r: u32| {
            let b = place(r as usize);
            a.traversal == b.traversal && a.position.abs_diff(b.position) > gap
        };
        out.extend(list.iter().filter(|&&(_, r)| other(r)).take(k).map(|&(_, r)| (i as u32, r)));
    }
    out
}

impl NullEvidence {
    /// The null of `sources` references under config key `key` from its pairs' verified inliers
    /// and compact-HOG cosines and its same-place pairs' cosines (empty where the map holds none).
    pub fn from_pairs(
        key: String,
        sources: usize,
        inliers: impl Iterator<Item = u32>,
        mut compact_hog: Vec<f32>,
        mut compact_hog_near: Vec<f32>,
    ) -> NullEvidence {
        let mut hist: Vec<u32> = vec![];
        let mut pairs = 0;
        for k in inliers {
            let k = k as usize;
            if hist.len() <= k {
                hist.resize(k + 1, 0);
            }
            hist[k] += 1;
            pairs += 1;
        }
        compact_hog.sort_by(f32::total_cmp);
        compact_hog_near.sort_by(f32::total_cmp);
        NullEvidence { key, sources: sources as u32, pairs, inliers: hist, compact_hog, compact_hog_near }
    }
}

/// What a kept null was measured on: the source's content, or its lineage (a stored map across its
/// generations) with the references it had then.
#[derive(Debug, Clone, PartialEq)]
enum Measured {
    Content(SourceKey),
    Lineage(u64, usize),
}

impl Measured {
    fn of(refs: &dyn RefSource) -> Measured {
        match refs.lineage() {
            Some(l) => Measured::Lineage(l, refs.len()),
            None => Measured::Content(SourceKey::of(refs)),
        }
    }
    /// Whether `null`, measured on `self`, serves `now`: the same content; or the same lineage
    /// within [`NullEvidence::serves_size`].
    fn serves(&self, null: &NullEvidence, now: &Measured) -> bool {
        match (self, now) {
            (Measured::Lineage(a, then), Measured::Lineage(b, n)) => a == b && null.serves_size(*then, *n),
            (a, b) => a == b,
        }
    }
}

/// Nulls measured in this process, most recent last: (what on, key) -> null.
static MEASURED: Mutex<Vec<(Measured, String, Arc<NullEvidence>)>> = Mutex::new(Vec::new());
/// Nulls kept at most (sources matched against in one process: a few).
const KEPT: usize = 16;

/// The null of `refs` under `cfg`: the one the source stores, if measured under `cfg`
/// ([`GlobalSource::stored_null`](crate::descriptors::source::GlobalSource::stored_null)); else the one kept in this process; else `measure`'s (then kept for the rest of the
/// process; for a stored map, across its generations until it doubles or halves).
pub fn kept_or(refs: &dyn RefSource, cfg: &Config, measure: impl FnOnce() -> Result<NullEvidence>) -> Result<Arc<NullEvidence>> {
    let (on, k) = (Measured::of(refs), key(cfg));
    // the one the map stores (measured at build under the same config): every process and every
    // shard of the map tests against it
    if let Some(n) = refs.stored_null().filter(|n| n.key == k) {
        return Ok(n);
    }
    let kept = MEASURED.lock().unwrap_or_else(|e| e.into_inner()).iter().rev().find(|e| e.1 == k && e.0.serves(&e.2, &on)).map(|e| e.2.clone());
    if let Some(n) = kept {
        return Ok(n);
    }
    let t = std::time::Instant::now();
    let n = Arc::new(measure()?);
    log::info!(
        "verified: the null of {} references measured in {:.0} ms ({} sources, {} pairs of other places verified; median {} inliers, 99th percentile {})",
        refs.len(),
        crate::util::ms_since(t),
        n.sources,
        n.pairs,
        n.inliers_quantile(0.5),
        n.inliers_quantile(0.99)
    );
    let mut kept = MEASURED.lock().unwrap_or_else(|e| e.into_inner());
    if kept.len() >= KEPT {
        kept.remove(0);
    }
    kept.push((on, k, n.clone()));
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn null(counts: &[u32]) -> NullEvidence {
        let mut inliers = vec![];
        for &k in counts {
            if inliers.len() <= k as usize {
                inliers.resize(k as usize + 1, 0);
            }
            inliers[k as usize] += 1;
        }
        NullEvidence { key: String::new(), sources: 0, pairs: counts.len() as u32, inliers, compact_hog: vec![], compact_hog_near: vec![] }
    }

    #[test]
    fn the_tail_is_the_sample_below_its_top_tenth_and_an_exponential_above() {
        // 100 null pairs: 0..=9 inliers ten times each
        let counts: Vec<u32> = (0..100).map(|i| i % 10).collect();
        let n = null(&counts);
        // within the body: the empirical survival function, (1 + #{x >= k}) / 101
        assert!((n.p_inliers(0) - 101.0 / 101.0).abs() < 1e-12);
        assert!((n.p_inliers(5) - 51.0 / 101.0).abs() < 1e-12);
        // above the threshold (the top tenth: all 9s) the tail decays, floored scale: monotone,
        // and far below 1 / 101 well above the sample
        let (p10, p20, p60) = (n.p_inliers(10), n.p_inliers(20), n.p_inliers(60));
        assert!(p10 < 11.0 / 101.0 && p20 < p10 && p60 < p20, "{p10} {p20} {p60}");
        assert!(p60 < 1e-6, "{p60}");
        // monotone everywhere
        let p: Vec<f64> = (0..80).map(|k| n.p_inliers(k)).collect();
        assert!(p.windows(2).all(|w| w[1] <= w[0]), "{p:?}");
    }

    #[test]
    fn a_heavy_null_makes_many_inliers_ordinary() {
        // a corridor: look-alikes of other places show 10 to 40 inliers
        let corridor: Vec<u32> = (0..300).map(|i| 10 + (i * 7919 % 31)).collect();
        let quiet: Vec<u32> = (0..300).map(|i| i % 6).collect();
        let (c, q) = (null(&corridor), null(&quiet));
        assert!(c.p_inliers(35) > 0.05, "{}", c.p_inliers(35));
        assert!(q.p_inliers(35) < 1e-4, "{}", q.p_inliers(35));
    }

    /// A stored map keeps its null across commits until it has doubled or halved; a null too small
    /// to test against serves only the size it was measured at; other content never shares one.
    #[test]
    fn a_growing_map_keeps_its_null_until_it_doubles() {
        let usable = null(&[3; 50]);
        let small = null(&[3; 5]);
        let at = |n: usize| Measured::Lineage(7, n);
        assert!(at(100).serves(&usable, &at(100)) && at(100).serves(&usable, &at(199)) && at(100).serves(&usable, &at(200)));
        assert!(!at(100).serves(&usable, &at(201)) && at(100).serves(&usable, &at(50)) && !at(100).serves(&usable, &at(49)));
        assert!(!at(100).serves(&usable, &Measured::Lineage(8, 100)), "another map");
        assert!(at(10).serves(&small, &at(10)) && !at(10).serves(&small, &at(11)));
    }

    #[test]
    fn too_small_a_sample_says_nothing() {
        let n = null(&[3, 4, 5]);
        assert_eq!(n.p_inliers(500), 1.0);
        let hogs = NullEvidence { compact_hog: vec![0.1, 0.2], compact_hog_near: vec![0.9; 50], ..n.clone() };
        assert_eq!(hogs.compact_hog_ratio(0.99), 1.0);
        let (pi, ph) = n.tail_and_ratio(&[Some(100), None], &[Some(0.9)]);
        assert_eq!((pi, ph), (vec![Some(1.0), None], vec![Some(1.0)]));
    }

    /// The compact HOGs count by how much more often the map's same-place pairs reach a cosine
    /// than its look-alikes do: tens of times or more where HOG tells the places apart, about once
    /// (or less) where the same place is no more alike than a look-alike; nothing without a
    /// same-place sample.
    #[test]
    fn the_compact_hogs_ratio_is_high_only_where_the_map_shows_hog_tells_its_places_apart() {
        let lookalikes: Vec<f32> = (0..1000).map(|i| 0.60 + 0.15 * (i as f32 / 1000.0)).collect();
        // a map whose same-place pairs are `n` cosines evenly from `from` to `from + span`
        let with_near = |n: usize, from: f32, span: f32| {
            let near = (0..n).map(|i| from + span * (i as f32 / n as f32)).collect();
            NullEvidence::from_pairs(String::new(), 100, std::iter::empty(), lookalikes.clone(), near)
        };
        let (apart, alike) = (with_near(200, 0.78, 0.1), with_near(200, 0.55, 0.2));
        // a cosine beyond every look-alike: most same-place pairs reach it on the first map (the
        // look-alikes' tail extrapolated with its scale floor, 0.05)
        assert!(apart.compact_hog_ratio(0.80) > 20.0, "{}", apart.compact_hog_ratio(0.80));
        assert!(alike.compact_hog_ratio(0.80) < 1.0, "{}", alike.compact_hog_ratio(0.80));
        // nor beyond the largest same-place cosine: both tails fitted alike, the null's alone
        // does not make a near-duplicate of another place likely
        for c in [0.9, 0.95, 1.0] {
            assert!(alike.compact_hog_ratio(c) < 2.0, "{c}: {}", alike.compact_hog_ratio(c));
        }
        // a cosine most look-alikes reach says nothing on either
        assert!(apart.compact_hog_ratio(0.5) < 1.1 && alike.compact_hog_ratio(0.5) < 1.1);
        let none = with_near(5, 0.9, 0.0);
        assert_eq!(none.compact_hog_ratio(0.8), 1.0);
        // many at once: the same ratios
        let (_, r) = apart.tail_and_ratio(&[], &[Some(0.80), None, Some(0.5)]);
        assert_eq!(r, vec![Some(apart.compact_hog_ratio(0.80) as f32), None, Some(apart.compact_hog_ratio(0.5) as f32)]);
    }

    #[test]
    fn same_place_pairs_are_a_sources_neighbours_on_its_traversal() {
        // references 0..20 on traversal 0, 20..30 on traversal 1; reference 7 removed
        let place = |i: usize| Place { traversal: (i >= 20) as u32, position: (i % 20) as u32 };
        let at = |p: Place| {
            let i = p.traversal as usize * 20 + p.position as usize;
            (i != 7 && p.position < 20 && i < 30).then_some(i)
        };
        // source 0: only 1 after it; 8: 9 (7 removed); 19: 18 (20 is another traversal); 25: 24, 26; 29: 28
        assert_eq!(pairs_beside(&place, &at, &[0, 8, 19, 25, 29]), vec![(0, 1), (1, 9), (2, 18), (3, 24), (3, 26), (4, 28)]);
        assert!(pairs_beside(&place, &at, &[]).is_empty());
    }

    #[test]
    fn sources_are_spread_and_null_pairs_keep_away_from_their_source() {
        assert_eq!(sources(10, 4), vec![0, 2, 5, 7]);
        assert_eq!(sources(3, 200), vec![0, 1, 2]);
        assert!(sources(0, 5).is_empty());
        // references 0..20 on traversal 0, 20..30 on traversal 1 (a second pass of a route)
        let place = |i: usize| Place { traversal: (i >= 20) as u32, position: (i % 20) as u32 };
        let list = |rs: &[u32]| rs.iter().map(|&r| (1.0, r)).collect::<Vec<_>>();
        let lists = vec![list(&[5, 6, 9, 2, 12, 25, 19, 18]), list(&[21, 3, 29, 27])];
        // source 5: 6, 9, 2 are within 4 positions; 25 is another traversal (maybe the same
        // place); 12, 19, 18 are other places, at most 2 kept, best first
        assert_eq!(pairs_apart(&place, &[5, 22], &lists, 4, 2), vec![(0, 12), (0, 19), (1, 29), (1, 27)]);
        assert!(pairs_apart(&place, &[], &[], 2, 5).is_empty());
    }
}
