//! Sequence matching on sparse rows (beyond the paper). SeqSLAM (Milford & Wyeth, "SeqSLAM:
//! Visual route-based navigation for sunny summer days and stormy winter nights", ICRA 2012)
//! scores straight lines through a difference matrix of every query frame against every
//! reference; SeqMatch (Garg & Milford, SeqNet, RA-L 2021) scores only the single-frame top-K.
//! Here each frame contributes a sparse row: the setting's scores of its candidates (widened by
//! their neighbours along the route), contrast-normalised, positive parts only. A ring keeps the
//! last `sequence.length` rows, nothing else, so the state is bounded whatever the map or the
//! stream.
//!
//! A trajectory ends at a place (traversal, position) at the newest frame and runs back at a
//! constant velocity `v` (positions per frame; 0 is a stop, negative drives backwards): `d` frames
//! back it is at position `floor(p - v d + 1/2)` of the same traversal, never another one. Its
//! score is the mean contribution over the frames where it lies on the traversal; it must lie on
//! it for at least half of the ring. Instead of walking every trajectory, every row entry votes
//! for the one endpoint per velocity whose trajectory passes through it ([`SequenceMatcher::push`]);
//! [`best_by_walking`] walks them all, the reference the votes are held to (tests below).

use crate::config::{Contrast, SequenceConfig};
use crate::descriptors::source::Place;
use serde::Serialize;
use std::collections::{HashMap, VecDeque};

/// A frame's evidence: positive contributions per place, each place at most once.
pub type Row = Vec<(Place, f32)>;

/// What the trajectory search over the ring gives, after every frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SequenceMatch {
    /// The match: the newest frame's strongest place near where the best trajectory ends
    /// (`sequence.refine`).
    pub place: Place,
    /// Where the best trajectory ends.
    pub end: Place,
    /// Mean contribution along it.
    pub score: f32,
    /// Its velocity, in positions per frame.
    pub velocity: f32,
    /// Frames of the ring it lies on the traversal for.
    pub frames: usize,
    /// `score` over the best score of a place more than `sequence.uniqueness_window` positions
    /// away (or on another traversal); [`UNIQUENESS_CAP`] where no such place scores.
    pub uniqueness: f32,
    /// `uniqueness >= sequence.min_uniqueness`, `frames >= sequence.min_frames`, and the newest
    /// frame agrees (`sequence.agreement`).
    pub accepted: bool,
}

/// The uniqueness of a match no other place competes with.
pub const UNIQUENESS_CAP: f32 = 1000.0;

/// Position `d` frames back along the trajectory ending at `end` with velocity `v`.
fn back(end: i64, v: f64, d: usize) -> i64 {
    (end as f64 - v * d as f64 + 0.5).floor() as i64
}

/// The endpoint whose trajectory (velocity `v`) passes position `p` `d` frames back: the one
/// integer `e` with `back(e, v, d) == p`.
fn endpoint(p: u32, v: f64, d: usize) -> i64 {
    (p as f64 + v * d as f64 - 0.5).ceil() as i64
}

/// Frames among the last `n` at which the trajectory (`end`, `v`) lies on a traversal of `len`.
fn cover(end: i64, v: f64, n: usize, len: u32) -> usize {
    (0..n).filter(|&d| (0..len as i64).contains(&back(end, v, d))).count()
}

/// The velocities `cfg` tries.
pub fn velocities(cfg: &SequenceConfig) -> Vec<f64> {
    let n = cfg.velocity_steps.max(1);
    match n {
        1 => vec![cfg.velocity_min],
        _ => (0..n).map(|i| cfg.velocity_min + (cfg.velocity_max - cfg.velocity_min) * i as f64 / (n - 1) as f64).collect(),
    }
}

/// The contributions of one frame's scores (`scored`: each place at most once, higher is better)
/// under `cfg.contrast`; `lens(t)` is the length of traversal `t`. References the frame did not
/// score count at its lowest score (the floor: its list held the best ones).
pub fn contributions(cfg: &SequenceConfig, scored: &[(Place, f32)], lens: &dyn Fn(u32) -> u32) -> Row {
    if scored.is_empty() {
        return vec![];
    }
    let floor = scored.iter().map(|x| x.1 as f64).fold(f64::INFINITY, f64::min);
    let z = |s: f64, mean: f64, var: f64| {
        let sd = var.max(0.0).sqrt();
        if sd > 1e-9 * (1.0 + mean.abs()) {
            (s - mean) / sd
        } else {
            0.0
        }
    };
    let mut out: Row = match cfg.contrast {
        Contrast::None => scored.iter().map(|&(p, s)| (p, (s as f64 - floor) as f32)).collect(),
        Contrast::Frame => {
            let n = scored.len() as f64;
            let mean = scored.iter().map(|x| x.1 as f64).sum::<f64>() / n;
            let var = scored.iter().map(|x| (x.1 as f64 - mean).powi(2)).sum::<f64>() / n;
            scored.iter().map(|&(p, s)| (p, z(s as f64, mean, var) as f32)).collect()
        }
        Contrast::Window => {
            let mut sorted = scored.to_vec();
            sorted.sort_by_key(|x| x.0);
            let r = cfg.contrast_window as u32;
            let mut out = Vec::with_capacity(sorted.len());
            for (i, &(p, s)) in sorted.iter().enumerate() {
                let len = lens(p.traversal).max(p.position + 1);
                let (lo, hi) = (p.position.saturating_sub(r), (p.position + r).min(len - 1));
                let same = |q: &Place| q.traversal == p.traversal && (lo..=hi).contains(&q.position);
                // the scored places of the window lie next to entry i in the sorted list
                let start = (0..i).rev().take_while(|&j| same(&sorted[j].0)).last().unwrap_or(i);
                let (mut k, mut sum, mut sum2) = (0usize, 0.0f64, 0.0f64);
                for &(_, v) in sorted[start..].iter().take_while(|q| same(&q.0)) {
                    k += 1;
                    sum += v as f64;
                    sum2 += (v as f64).powi(2);
                }
                let m = (hi - lo + 1) as f64;
                let rest = m - k as f64;
                let mean = (sum + rest * floor) / m;
                let var = (sum2 + rest * floor * floor) / m - mean * mean;
                out.push((p, z(s as f64, mean, var) as f32));
            }
            out
        }
    };
    out.retain(|x| x.1 > 0.0 && x.1.is_finite());
    out
}

/// The best trajectory score of each endpoint: (score, velocity index, frames covered).
type Ends = HashMap<Place, (f64, usize, usize)>;

/// The ring of the last rows and the trajectory search over it.
#[derive(Debug, Clone)]
pub struct SequenceMatcher {
    cfg: SequenceConfig,
    velocities: Vec<f64>,
    /// Newest first.
    rows: VecDeque<Row>,
}

impl SequenceMatcher {
    /// An empty ring with the parameters of `cfg`.
    pub fn new(cfg: &SequenceConfig) -> SequenceMatcher {
        SequenceMatcher { cfg: cfg.clone(), velocities: velocities(cfg), rows: VecDeque::with_capacity(cfg.length) }
    }

    /// Frames in the ring (at most `sequence.length`).
    pub fn frames(&self) -> usize {
        self.rows.len()
    }

    /// Entries held over all rows (bounded by `length` x the entries of a row).
    pub fn entries(&self) -> usize {
        self.rows.iter().map(Vec::len).sum()
    }

    /// Forgets every frame (a new stream).
    pub fn clear(&mut self) {
        self.rows.clear();
    }

    /// Every place the ring holds evidence for (a place once per row it is in).
    pub fn places(&self) -> impl Iterator<Item = Place> + '_ {
        self.rows.iter().flatten().map(|e| e.0)
    }

    /// Moves every entry to the place `f` gives (after the map changed under the stream), or drops
    /// it where `f` gives none.
    pub fn remap(&mut self, mut f: impl FnMut(Place) -> Option<Place>) {
        for row in &mut self.rows {
            *row = row.iter().filter_map(|&(p, c)| f(p).map(|q| (q, c))).collect();
        }
    }

    /// Adds the newest frame's row (see [`contributions`]) and returns the best trajectory through
    /// the ring, or `None` where no place has evidence. `lens(t)`: the length of traversal `t`.
    pub fn push(&mut self, row: Row, lens: &dyn Fn(u32) -> u32) -> Option<SequenceMatch> {
        self.rows.push_front(row);
        self.rows.truncate(self.cfg.length.max(1));
        let ends = self.vote(lens);
        self.decide(&ends)
    }

    /// Every row entry votes, per velocity, for the endpoint whose trajectory passes through it.
    fn vote(&self, lens: &dyn Fn(u32) -> u32) -> Ends {
        let n = self.rows.len();
        let need = n.div_ceil(2).max(1);
        let mut ends: Ends = HashMap::new();
        for (vi, &v) in self.velocities.iter().enumerate() {
            let mut sums: HashMap<Place, f64> = HashMap::new();
            for (d, row) in self.rows.iter().enumerate() {
                for &(p, c) in row {
                    let e = endpoint(p.position, v, d);
                    if (0..lens(p.traversal) as i64).contains(&e) {
                        *sums.entry(Place { traversal: p.traversal, position: e as u32 }).or_default() += c as f64;
                    }
                }
            }
            for (place, sum) in sums {
                let frames = cover(place.position as i64, v, n, lens(place.traversal));
                if frames < need {
                    continue;
                }
                let cand = (sum / frames as f64, vi, frames);
                let e = ends.entry(place).or_insert(cand);
                if better(cand, *e, &self.velocities) {
                    *e = cand;
                }
            }
        }
        ends
    }

    fn decide(&self, ends: &Ends) -> Option<SequenceMatch> {
        decide(&self.cfg, &self.velocities, ends, self.rows.front().map_or(&[][..], Vec::as_slice))
    }
}

/// Whether trajectory score `a` beats `b` at one endpoint: higher score, then more frames, then
/// the velocity closer to 1 (then the lower index), so that the result never depends on the
/// order of a hash map.
fn better(a: (f64, usize, usize), b: (f64, usize, usize), v: &[f64]) -> bool {
    let key = |x: (f64, usize, usize)| (x.0, x.2, -(v[x.1] - 1.0).abs(), std::cmp::Reverse(x.1));
    key(a).partial_cmp(&key(b)) == Some(std::cmp::Ordering::Greater)
}

/// The best endpoint of `ends`, refined by the newest frame's row `newest`: a constant-velocity
/// line through frames of a varying speed may end a position or two off, so the match is the
/// newest frame's strongest place within `sequence.refine` positions of the endpoint (the endpoint
/// itself where the frame has none there).
fn decide(cfg: &SequenceConfig, velocities: &[f64], ends: &Ends, newest: &[(Place, f32)]) -> Option<SequenceMatch> {
    // the best endpoint: highest score, ties to the lower place (a total order)
    let (&place, &(score, vi, frames)) = ends.iter().filter(|e| e.1 .0 > 0.0).max_by(|a, b| a.1 .0.total_cmp(&b.1 .0).then_with(|| b.0.cmp(a.0)))?;
    let w = cfg.uniqueness_window as u32;
    let apart = |p: &Place| p.traversal != place.traversal || p.position.abs_diff(place.position) > w;
    let second = ends.iter().filter(|e| apart(e.0)).map(|e| e.1 .0).fold(0.0f64, f64::max);
    let uniqueness = if second > 0.0 { ((score / second) as f32).min(UNIQUENESS_CAP) } else { UNIQUENESS_CAP };
    let r = cfg.refine as u32;
    let near = newest
        .iter()
        .filter(|(p, _)| p.traversal == place.traversal && p.position.abs_diff(place.position) <= r)
        .max_by(|a, b| a.1.total_cmp(&b.1).then_with(|| b.0.cmp(&a.0)));
    let refined = near.map_or(place, |e| e.0);
    // the newest frame agrees: its evidence there is at least `agreement` of its strongest
    let strongest = newest.iter().map(|e| e.1).fold(0.0f32, f32::max);
    let agrees = near.map_or(0.0, |e| e.1) as f64 >= cfg.agreement * strongest as f64;
    Some(SequenceMatch {
        place: refined,
        end: place,
        score: score as f32,
        velocity: velocities[vi] as f32,
        frames,
        uniqueness,
        accepted: uniqueness as f64 >= cfg.min_uniqueness && frames >= cfg.min_frames && agrees,
    })
}

/// The reference the votes are held to: every trajectory (each position of each traversal, each
/// velocity) walked frame by frame through `rows` (newest first), the best taken as
/// [`SequenceMatcher::push`] does.
pub fn best_by_walking(cfg: &SequenceConfig, rows: &[Row], traversals: &[u32]) -> Option<SequenceMatch> {
    let velocities = velocities(cfg);
    let n = rows.len();
    let need = n.div_ceil(2).max(1);
    let lookup: Vec<HashMap<Place, f32>> = rows.iter().map(|r| r.iter().copied().collect()).collect();
    let mut ends: Ends = HashMap::new();
    for (t, &len) in traversals.iter().enumerate() {
        for e in 0..len {
            for (vi, &v) in velocities.iter().enumerate() {
                let (mut sum, mut frames, mut any) = (0.0f64, 0usize, false);
                for (d, row) in lookup.iter().enumerate() {
                    let q = back(e as i64, v, d);
                    if (0..len as i64).contains(&q) {
                        frames += 1;
                        if let Some(&c) = row.get(&Place { traversal: t as u32, position: q as u32 }) {
                            sum += c as f64;
                            any = true;
                        }
                    }
                }
                if !any || frames < need {
                    continue;
                }
                let cand = (sum / frames as f64, vi, frames);
                let place = Place { traversal: t as u32, position: e };
                let cur = ends.entry(place).or_insert(cand);
                if better(cand, *cur, &velocities) {
                    *cur = cand;
                }
            }
        }
    }
    decide(cfg, &velocities, &ends, rows.first().map_or(&[][..], Vec::as_slice))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn place(t: u32, p: u32) -> Place {
        Place { traversal: t, position: p }
    }

    /// Votes and walks agree on random rows over two traversals, for random velocity ranges
    /// (backwards ones included) and ring lengths.
    #[test]
    fn votes_equal_walking_every_trajectory() {
        let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig { cases: 300, ..Default::default() });
        let strategy = (
            1usize..12,
            -2.0f64..1.0,
            0.0f64..2.5,
            1usize..7,
            proptest::collection::vec(proptest::collection::vec((0u32..2, 0u32..40, 0.01f32..3.0), 0..12), 1..12),
        );
        runner
            .run(&strategy, |(length, vmin, span, steps, rows)| {
                let cfg =
                    SequenceConfig { length, velocity_min: vmin, velocity_max: vmin + span, velocity_steps: steps, ..SequenceConfig::default() };
                let lens = [40u32, 25];
                let rows: Vec<Row> = rows
                    .into_iter()
                    .map(|r| {
                        let mut m: HashMap<Place, f32> = HashMap::new();
                        for (t, p, c) in r {
                            m.insert(place(t, p % lens[t as usize]), c);
                        }
                        let mut row: Row = m.into_iter().collect();
                        row.sort_by_key(|x| x.0);
                        row
                    })
                    .collect();
                let mut m = SequenceMatcher::new(&cfg);
                let mut got = None;
                for r in rows.iter().rev() {
                    got = m.push(r.clone(), &|t| lens[t as usize]);
                }
                let kept: Vec<Row> = rows.iter().take(length).cloned().collect();
                let want = best_by_walking(&cfg, &kept, &lens);
                prop_assert_eq!(got, want);
                Ok(())
            })
            .unwrap();
    }

    /// A walk at one position per frame along traversal 0 beats a brighter but scattered alias.
    #[test]
    fn a_consistent_trajectory_beats_single_frame_aliases() {
        let run = |agreement: f64| {
            let cfg = SequenceConfig { contrast: Contrast::None, agreement, ..SequenceConfig::default() };
            let mut m = SequenceMatcher::new(&cfg);
            let mut last = None;
            for t in 0..10u32 {
                // the true place 20 + t scores 1.0; an alias at a random-looking place scores 1.5
                let row = vec![(place(0, 20 + t), 1.0), (place(0, (t * 37) % 90), 1.5)];
                last = m.push(row, &|_| 100);
            }
            last.unwrap()
        };
        let last = run(0.0);
        assert_eq!(last.place, place(0, 29));
        assert_eq!(last.velocity, 1.0);
        assert!(last.accepted, "{last:?}");
        // the newest frame gives the match 1.0 of its strongest 1.5: below an agreement of 0.8
        let strict = run(0.8);
        assert_eq!(strict.place, place(0, 29));
        assert!(!strict.accepted, "{strict:?}");
        assert!(run(0.6).accepted);
    }

    /// A trajectory never crosses into another traversal: evidence split over two traversals at
    /// the same positions does not add up.
    #[test]
    fn trajectories_stay_on_their_traversal() {
        let cfg = SequenceConfig { contrast: Contrast::None, ..SequenceConfig::default() };
        let mut m = SequenceMatcher::new(&cfg);
        let mut last = None;
        for t in 0..10u32 {
            // even frames on traversal 0, odd ones on traversal 1, both along positions 10 + t;
            // traversal 1 also has one frame's strong evidence elsewhere
            let tr = t % 2;
            last = m.push(vec![(place(tr, 10 + t), 1.0)], &|_| 100);
        }
        let last = last.unwrap();
        // each traversal's trajectory has half the frames' evidence: 0.5, not 1.0
        assert!((last.score - 0.5).abs() < 1e-6, "{last:?}");
    }

    #[test]
    fn window_contrast_raises_a_local_peak_and_drops_the_rest() {
        let cfg = SequenceConfig { contrast: Contrast::Window, ..SequenceConfig::default() };
        let scored = vec![(place(0, 50), 2.0), (place(0, 51), 1.0), (place(0, 80), 1.5), (place(0, 81), 1.5), (place(0, 82), 1.5)];
        let row = contributions(&cfg, &scored, &|_| 200);
        let c = |p: u32| row.iter().find(|x| x.0.position == p).map(|x| x.1);
        // 50 stands out of its floor-filled window more than 80-82, three equal scores do out of
        // theirs (z 4.47 against 2.45); 51 is at the floor, below its window's mean: nothing
        assert!(c(50).unwrap() > c(81).unwrap(), "{row:?}");
        assert!((c(50).unwrap() - 4.47).abs() < 0.01 && (c(81).unwrap() - 2.45).abs() < 0.01, "{row:?}");
        assert_eq!(c(51), None, "{row:?}");
        assert!(row.iter().all(|x| x.1 > 0.0));
    }

    #[test]
    fn an_empty_row_and_an_empty_ring_have_no_match() {
        let cfg = SequenceConfig::default();
        assert!(contributions(&cfg, &[], &|_| 10).is_empty());
        let mut m = SequenceMatcher::new(&cfg);
        assert_eq!(m.push(vec![], &|_| 10), None);
        assert_eq!(best_by_walking(&cfg, &[vec![]], &[10]), None);
    }
}
