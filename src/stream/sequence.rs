//! Sequence matching on sparse rows (beyond the paper). SeqSLAM (Milford & Wyeth, "SeqSLAM:
//! Visual route-based navigation for sunny summer days and stormy winter nights", ICRA 2012)
//! scores straight lines through a difference matrix of every query frame against every
//! reference; SeqMatch (Garg & Milford, SeqNet, RA-L 2021) scores only the single-frame top-K.
//! Here each frame contributes a sparse row: the setting's scores of its candidates (widened by
//! their neighbours along the route), contrast-normalised, positive parts only. A ring keeps the
//! last `sequence.length` rows, nothing else, so the state is bounded whatever the map or the
//! stream.
//!
//! A trajectory runs through the ring from the oldest frame to the newest along one traversal,
//! never another one. Its velocity (positions per frame, one of `velocity_steps` values from
//! `velocity_min` to `velocity_max`; 0 is a stop, negative drives backwards) may change by one
//! step from one frame to the next, at a cost of `velocity_change` per step: a camera that speeds
//! up, slows down or stops is followed, where SeqSLAM's straight lines end off the place (the
//! online graph search of Vysotska & Stachniss, RA-L 2016, and the HMM of Hansen & Browning,
//! ICRA 2014, make the same move). Positions are tracked in sub-steps of a place (one velocity
//! step), so a velocity of 0.75 moves three sub-steps a frame. Its score is the sum of the
//! contributions of the places it passes, less the velocity changes' cost, over the ring's
//! frames. The best trajectory ending at each place comes from a dynamic programme over the
//! places within reach of the ring's evidence ([`SequenceMatcher::push`]); [`best_by_walking`]
//! walks every trajectory instead and is the reference the programme is held to (tests below).

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
    /// The contributions of the places it passes, less its velocity changes' cost
    /// (`sequence.velocity_change` a step), over the ring's frames.
    pub score: f32,
    /// Its velocity at the newest frame, in positions per frame.
    pub velocity: f32,
    /// Frames of the ring it lies on the traversal for.
    pub frames: usize,
    /// `score` over the best score of a place more than `sequence.uniqueness_window` positions
    /// away (at most half the traversal; or on another traversal); [`UNIQUENESS_CAP`] where no
    /// such place scores.
    pub uniqueness: f32,
    /// How alike the newest frame's evidence is to the frame's before it (the cosine of their
    /// rows): 1 where a camera stands still.
    pub stillness: f32,
    /// `uniqueness >= sequence.min_uniqueness`, `frames >= sequence.min_frames`, the
    /// trajectory moves (|velocity| at least `sequence.stop_velocity`) or the frames stand still
    /// (`stillness` at least `sequence.stillness`): a standing trajectory is taken only where the
    /// camera stands, not where one place matches every frame of a moving camera; and the newest
    /// frame vouches for it (`sequence.support`).
    pub accepted: bool,
    /// The newest frame gives a place within `sequence.refine` positions of the trajectory's
    /// end at least `sequence.support` of its strongest evidence (what acceptance asks of it).
    pub supported: bool,
}

/// The uniqueness of a match no other place competes with.
pub const UNIQUENESS_CAP: f32 = 1000.0;

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

/// The best trajectory ending at each place: (score, velocity index at the newest frame, frames
/// on the traversal).
type Ends = HashMap<Place, (f64, usize, usize)>;

/// The velocities a trajectory may take and how far each moves in sub-steps of a place.
#[derive(Debug, Clone)]
struct Grid {
    velocities: Vec<f64>,
    /// Sub-steps moved per frame at each velocity.
    moves: Vec<i64>,
    /// Sub-steps per place: one velocity step (1/4 of a place at the defaults), at most 8.
    sub: i64,
}

impl Grid {
    fn new(cfg: &SequenceConfig) -> Grid {
        let velocities = velocities(cfg);
        let step = match velocities.len() {
            0 | 1 => 1.0,
            n => (velocities[n - 1] - velocities[0]) / (n - 1) as f64,
        };
        let sub = if step > 0.0 { (1.0 / step).round().clamp(1.0, 8.0) as i64 } else { 1 };
        let moves = velocities.iter().map(|v| (v * sub as f64).round() as i64).collect();
        Grid { velocities, moves, sub }
    }

    /// Places a trajectory moves at most over `n` frames (its positions all lie within this many
    /// places of any place it passes).
    fn reach(&self, n: usize) -> i64 {
        let fastest = self.moves.iter().map(|m| m.abs()).max().unwrap_or(0);
        (fastest * n.saturating_sub(1) as i64 + self.sub - 1) / self.sub + 1
    }

    /// The place of sub-step `s`.
    fn place(&self, s: i64) -> i64 {
        s.div_euclid(self.sub)
    }
}

/// The ring of the last rows and the trajectory search over it.
#[derive(Debug, Clone)]
pub struct SequenceMatcher {
    cfg: SequenceConfig,
    grid: Grid,
    /// Newest first.
    rows: VecDeque<Row>,
    /// What `velocity_min` and `velocity_max` are multiplied by ([`SequenceMatcher::set_velocity_scale`]).
    scale: f64,
}

impl SequenceMatcher {
    /// An empty ring with the parameters of `cfg` (its `velocity_scale` where set, else 1).
    pub fn new(cfg: &SequenceConfig) -> SequenceMatcher {
        let mut m = SequenceMatcher { cfg: cfg.clone(), grid: Grid::new(cfg), rows: VecDeque::with_capacity(cfg.length), scale: 1.0 };
        m.set_velocity_scale(cfg.velocity_scale.unwrap_or(1.0));
        m
    }

    /// Multiplies the velocity range by `scale` from the next frame on (a stream at another
    /// frame rate than the map's); the ring is kept (the search runs over it anew each frame).
    pub fn set_velocity_scale(&mut self, scale: f64) {
        let scaled = SequenceConfig { velocity_min: self.cfg.velocity_min * scale, velocity_max: self.cfg.velocity_max * scale, ..self.cfg.clone() };
        self.grid = Grid::new(&scaled);
        self.scale = scale;
    }

    /// What the velocity range is multiplied by.
    pub fn velocity_scale(&self) -> f64 {
        self.scale
    }

    /// The slowest and fastest velocities tried, in positions per frame (the range scaled).
    pub fn velocity_range(&self) -> (f64, f64) {
        let v = &self.grid.velocities;
        (v.first().copied().unwrap_or(0.0), v.last().copied().unwrap_or(0.0))
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
        let rows: Vec<&[(Place, f32)]> = self.rows.iter().map(Vec::as_slice).collect();
        let still = stillness(rows[0], rows.get(1).copied().unwrap_or(&[]));
        let ends = search(&self.cfg, &self.grid, &rows, lens);
        decide(&self.cfg, &self.grid, &ends, &rows, still, lens)
    }
}

/// How alike the newest two rows of the ring are: the cosine of their contributions as vectors
/// over the places (1 where the frames gave the same evidence, as a camera standing still does;
/// 0 where either row is empty or the ring holds one frame).
fn stillness(a: &[(Place, f32)], b: &[(Place, f32)]) -> f32 {
    let norm = |r: &[(Place, f32)]| r.iter().map(|e| (e.1 as f64).powi(2)).sum::<f64>().sqrt();
    let (na, nb) = (norm(a), norm(b));
    if na == 0.0 || nb == 0.0 {
        return 0.0;
    }
    let other: HashMap<Place, f32> = b.iter().copied().collect();
    let dot: f64 = a.iter().filter_map(|(p, c)| other.get(p).map(|d| *c as f64 * *d as f64)).sum();
    // rounding must not keep identical rows below 1
    (dot / (na * nb)).clamp(0.0, 1.0).max(if a == b { 1.0 } else { 0.0 }) as f32
}

/// One run of places of a traversal that the search treats alone: every trajectory through
/// evidence inside it stays inside it.
struct Span {
    traversal: u32,
    /// Places `lo..hi`, reaching beyond the traversal's ends where trajectories may start off it.
    lo: i64,
    hi: i64,
    /// The most any trajectory in it can score: each frame's strongest evidence in it, summed.
    bound: f64,
}

/// The spans of the ring's evidence: places within reach of an entry, merged, per traversal,
/// strongest bound first.
fn spans(grid: &Grid, rows: &[&[(Place, f32)]]) -> Vec<Span> {
    let reach = grid.reach(rows.len());
    let mut by_traversal: HashMap<u32, Vec<i64>> = HashMap::new();
    for row in rows {
        for (p, _) in row.iter() {
            by_traversal.entry(p.traversal).or_default().push(p.position as i64);
        }
    }
    let mut out = Vec::new();
    for (t, mut pos) in by_traversal {
        pos.sort_unstable();
        pos.dedup();
        let mut runs: Vec<(i64, i64)> = Vec::new();
        for p in pos {
            match runs.last_mut() {
                Some(r) if p - reach <= r.1 => r.1 = p + reach + 1,
                _ => runs.push((p - reach, p + reach + 1)),
            }
        }
        for (lo, hi) in runs {
            let bound = rows
                .iter()
                .map(|row| {
                    let inside = |e: &&(Place, f32)| e.0.traversal == t && (lo..hi).contains(&(e.0.position as i64));
                    row.iter().filter(inside).map(|e| e.1 as f64).fold(0.0, f64::max)
                })
                .sum::<f64>();
            out.push(Span { traversal: t, lo, hi, bound });
        }
    }
    out.sort_by(|a, b| b.bound.total_cmp(&a.bound).then((a.traversal, a.lo).cmp(&(b.traversal, b.lo))));
    out
}

/// Whether trajectory `a` beats `b` at one endpoint: higher score, then more frames on the
/// traversal, then the velocity closer to 1 (then the lower index), so that the result never
/// depends on the order of the search.
fn better(a: (f64, usize, usize), b: (f64, usize, usize), v: &[f64]) -> bool {
    let key = |x: (f64, usize, usize)| (x.0, x.2, -(v[x.1] - 1.0).abs(), std::cmp::Reverse(x.1));
    key(a).partial_cmp(&key(b)) == Some(std::cmp::Ordering::Greater)
}

/// A trajectory's running (sum, frames on the traversal) in the programme.
type Cell = (f64, u32);
const NONE: Cell = (f64::NEG_INFINITY, 0);

/// The best trajectory ending at each place of the spans that can matter, strongest span first:
/// a span whose bound is below the best score of a place apart from the best so far can change
/// neither.
fn search(cfg: &SequenceConfig, grid: &Grid, rows: &[&[(Place, f32)]], lens: &dyn Fn(u32) -> u32) -> Ends {
    let n = rows.len();
    let mut ends: Ends = HashMap::new();
    if n == 0 {
        return ends;
    }
    for span in spans(grid, rows) {
        if let Some((best, _)) = best_end(&ends) {
            if span.bound / (n as f64) < second_apart(cfg, &ends, best, lens) {
                break;
            }
        }
        run_span(cfg, grid, rows, &span, lens(span.traversal), &mut ends);
    }
    ends
}

/// The programme over one span: `v[j][x]`, the best (sum, frames on the traversal) of the
/// trajectories at sub-step `x` of the span whose last move was at velocity `j`, from the oldest
/// frame to the newest.
fn run_span(cfg: &SequenceConfig, grid: &Grid, rows: &[&[(Place, f32)]], span: &Span, len: u32, ends: &mut Ends) {
    let (n, sub, nv) = (rows.len(), grid.sub, grid.moves.len());
    let width = ((span.hi - span.lo) * sub) as usize;
    let place_of = |x: usize| span.lo + x as i64 / sub;
    let on = |p: i64| (0..len as i64).contains(&p);
    // each frame's evidence per place of the span
    let evidence = |row: &[(Place, f32)]| -> Vec<f64> {
        let mut e = vec![0.0; (span.hi - span.lo) as usize];
        for (p, c) in row {
            let q = p.position as i64;
            if p.traversal == span.traversal && (span.lo..span.hi).contains(&q) {
                e[(q - span.lo) as usize] = *c as f64;
            }
        }
        e
    };
    let ev = evidence(rows[n - 1]);
    let mut v: Vec<Cell> = Vec::with_capacity(nv * width);
    for _ in 0..nv {
        v.extend((0..width).map(|x| (ev[(x as i64 / sub) as usize], u32::from(on(place_of(x))))));
    }
    let mut next = vec![NONE; nv * width];
    for d in (0..n - 1).rev() {
        let ev = evidence(rows[d]);
        for j in 0..nv {
            let m = grid.moves[j];
            for x in 0..width {
                let from = x as i64 - m;
                let mut best = NONE;
                if (0..width as i64).contains(&from) {
                    for k in j.saturating_sub(1)..(j + 2).min(nv) {
                        let c = v[k * width + from as usize];
                        let cand = (c.0 - cfg.velocity_change * k.abs_diff(j) as f64, c.1);
                        if cand.0 > best.0 || (cand.0 == best.0 && cand.1 > best.1) {
                            best = cand;
                        }
                    }
                }
                let p = place_of(x);
                next[j * width + x] = match best.0.is_finite() {
                    true => (ev[(p - span.lo) as usize] + best.0, best.1 + u32::from(on(p))),
                    false => NONE,
                };
            }
        }
        std::mem::swap(&mut v, &mut next);
    }
    for j in 0..nv {
        for x in 0..width {
            let p = place_of(x);
            let c = v[j * width + x];
            if !on(p) || !c.0.is_finite() {
                continue;
            }
            let cand = (c.0 / n as f64, j, c.1 as usize);
            let e = ends.entry(Place { traversal: span.traversal, position: p as u32 }).or_insert(cand);
            if better(cand, *e, &grid.velocities) {
                *e = cand;
            }
        }
    }
}

/// The best endpoint: highest score, ties to the lower place (a total order).
fn best_end(ends: &Ends) -> Option<(Place, (f64, usize, usize))> {
    ends.iter().filter(|e| e.1 .0 > 0.0).max_by(|a, b| a.1 .0.total_cmp(&b.1 .0).then_with(|| b.0.cmp(a.0))).map(|(p, v)| (*p, *v))
}

/// The uniqueness window at `place`: `uniqueness_window`, at most half its traversal (so that a
/// short traversal still has places apart to compete).
fn window(cfg: &SequenceConfig, place: Place, lens: &dyn Fn(u32) -> u32) -> u32 {
    (cfg.uniqueness_window as u32).min(lens(place.traversal).saturating_sub(1) / 2)
}

/// The best score of a place apart from `place` (0 where none scores).
fn second_apart(cfg: &SequenceConfig, ends: &Ends, place: Place, lens: &dyn Fn(u32) -> u32) -> f64 {
    let w = window(cfg, place, lens);
    let apart = |p: &Place| p.traversal != place.traversal || p.position.abs_diff(place.position) > w;
    ends.iter().filter(|e| apart(e.0)).map(|e| e.1 .0).fold(0.0f64, f64::max)
}

/// The match from the best endpoint of `ends`, refined by the newest frame's row `rows[0]`: the
/// newest frame's strongest place within `sequence.refine` positions of the endpoint, where the
/// frame gives it at least `refine_share` of its strongest evidence (the endpoint itself
/// otherwise).
fn decide(cfg: &SequenceConfig, grid: &Grid, ends: &Ends, rows: &[&[(Place, f32)]], still: f32, lens: &dyn Fn(u32) -> u32) -> Option<SequenceMatch> {
    let (place, (score, vi, frames)) = best_end(ends)?;
    let second = second_apart(cfg, ends, place, lens);
    let uniqueness = if second > 0.0 { ((score / second) as f32).min(UNIQUENESS_CAP) } else { UNIQUENESS_CAP };
    let newest = rows.first().copied().unwrap_or(&[]);
    let r = cfg.refine as u32;
    let strongest = newest.iter().map(|e| e.1).fold(0.0f32, f32::max);
    let near = newest
        .iter()
        .filter(|(p, _)| p.traversal == place.traversal && p.position.abs_diff(place.position) <= r)
        .max_by(|a, b| a.1.total_cmp(&b.1).then_with(|| b.0.cmp(&a.0)))
        .filter(|e| e.1 as f64 >= cfg.refine_share * strongest as f64);
    // the newest frame vouches for the match: evidence near the end, at least `support` of its strongest
    let supported = newest.iter().any(|(p, c)| {
        p.traversal == place.traversal && p.position.abs_diff(place.position) <= r && *c > 0.0 && *c as f64 >= cfg.support * strongest as f64
    });
    let velocity = grid.velocities[vi];
    let moving = velocity.abs() >= cfg.stop_velocity;
    Some(SequenceMatch {
        place: near.map_or(place, |e| e.0),
        end: place,
        score: score as f32,
        velocity: velocity as f32,
        frames,
        uniqueness,
        stillness: still,
        accepted: uniqueness as f64 >= cfg.min_uniqueness && frames >= cfg.min_frames && (moving || still as f64 >= cfg.stillness) && supported,
        supported,
    })
}

/// The reference the programme is held to: every trajectory (each start of each traversal,
/// within reach of its ends, each sequence of velocities changing by at most one step a frame)
/// walked through `rows` (newest first), the best taken as [`SequenceMatcher::push`] does.
/// Exponential in the ring's length: for tests.
pub fn best_by_walking(cfg: &SequenceConfig, rows: &[Row], traversals: &[u32]) -> Option<SequenceMatch> {
    let grid = Grid::new(cfg);
    let n = rows.len();
    let lens = |t: u32| traversals.get(t as usize).copied().unwrap_or(0);
    let refs: Vec<&[(Place, f32)]> = rows.iter().map(Vec::as_slice).collect();
    let still = stillness(refs.first().copied().unwrap_or(&[]), refs.get(1).copied().unwrap_or(&[]));
    let lookup: Vec<HashMap<Place, f32>> = rows.iter().map(|r| r.iter().copied().collect()).collect();
    let mut ends: Ends = HashMap::new();
    if n == 0 {
        return None;
    }
    let reach = grid.reach(n) * grid.sub;
    let nv = grid.moves.len();
    for (t, &len) in traversals.iter().enumerate() {
        let t = t as u32;
        let ev = |d: usize, p: i64| -> f64 {
            match u32::try_from(p) {
                Ok(q) => lookup[d].get(&Place { traversal: t, position: q }).map_or(0.0, |c| *c as f64),
                Err(_) => 0.0,
            }
        };
        let on = |p: i64| (0..len as i64).contains(&p);
        // depth-first over (sub-step, velocity of the last move, sum, frames on), oldest first
        let mut stack: Vec<(usize, i64, Option<usize>, f64, u32)> = Vec::new();
        for s in -reach..(len as i64) * grid.sub + reach {
            let p = grid.place(s);
            stack.push((n - 1, s, None, ev(n - 1, p), u32::from(on(p))));
        }
        while let Some((d, s, j, sum, frames)) = stack.pop() {
            if d == 0 {
                let (p, j) = (grid.place(s), j.unwrap_or(0));
                if on(p) {
                    let cand = (sum / n as f64, if n == 1 { 0 } else { j }, frames as usize);
                    let place = Place { traversal: t, position: p as u32 };
                    if n == 1 {
                        // a ring of one frame: every velocity ends here alike
                        for k in 0..nv {
                            let c = (cand.0, k, cand.2);
                            let e = ends.entry(place).or_insert(c);
                            if better(c, *e, &grid.velocities) {
                                *e = c;
                            }
                        }
                        continue;
                    }
                    let e = ends.entry(place).or_insert(cand);
                    if better(cand, *e, &grid.velocities) {
                        *e = cand;
                    }
                }
                continue;
            }
            let range = match j {
                None => 0..nv,
                Some(j) => j.saturating_sub(1)..(j + 2).min(nv),
            };
            for k in range {
                let s2 = s + grid.moves[k];
                let p = grid.place(s2);
                let pen = j.map_or(0.0, |j| cfg.velocity_change * j.abs_diff(k) as f64);
                stack.push((d - 1, s2, Some(k), ev(d - 1, p) + (sum - pen), frames + u32::from(on(p))));
            }
        }
    }
    decide(cfg, &grid, &ends, &refs, still, &lens)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn place(t: u32, p: u32) -> Place {
        Place { traversal: t, position: p }
    }

    /// The programme and the walk agree on random rows over two traversals, for random velocity
    /// ranges (backwards ones included), velocity-change costs and ring lengths. Contributions
    /// are multiples of 1/8 so that every sum is exact and ties are ties on both sides.
    #[test]
    fn the_programme_equals_walking_every_trajectory() {
        let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig { cases: 1000, ..Default::default() });
        let strategy = (
            1usize..6,
            -2.0f64..1.0,
            0.0f64..2.5,
            1usize..6,
            0u32..12,
            proptest::collection::vec(proptest::collection::vec((0u32..2, 0u32..60, 1u32..24), 0..24), 1..6),
        );
        runner
            .run(&strategy, |(length, vmin, span, steps, change, rows)| {
                let cfg = SequenceConfig {
                    length,
                    velocity_min: vmin,
                    velocity_max: vmin + span,
                    velocity_steps: steps,
                    velocity_change: change as f64 / 8.0,
                    refine: 1,
                    refine_share: 0.5,
                    ..SequenceConfig::default()
                };
                let lens = [60u32, 25];
                let rows: Vec<Row> = rows
                    .into_iter()
                    .map(|r| {
                        let mut m: HashMap<Place, f32> = HashMap::new();
                        for (t, p, c) in r {
                            m.insert(place(t, p % lens[t as usize]), c as f32 / 8.0);
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

    /// A walk at one position per frame along traversal 0 beats a brighter but scattered alias,
    /// and is accepted.
    #[test]
    fn a_consistent_trajectory_beats_single_frame_aliases() {
        let cfg = SequenceConfig { contrast: Contrast::None, ..SequenceConfig::default() };
        let mut m = SequenceMatcher::new(&cfg);
        let mut last = None;
        for t in 0..10u32 {
            // the true place 20 + t scores 1.0; an alias at a random-looking place scores 1.5
            let row = vec![(place(0, 20 + t), 1.0), (place(0, (t * 37) % 90), 1.5)];
            last = m.push(row, &|_| 100);
        }
        let last = last.unwrap();
        assert_eq!(last.end, place(0, 29));
        assert_eq!(last.velocity, 1.0);
        assert!(last.accepted, "{last:?}");
        // the newest frame's strongest evidence near the end is the end itself: no refinement
        assert_eq!(last.place, place(0, 29));
    }

    /// A camera that drives at 1 place a frame and then stops is followed to where it stands;
    /// SeqSLAM's straight lines (a velocity change that costs too much to take) run on past it.
    #[test]
    fn a_change_of_speed_is_followed() {
        let run = |change: f64| {
            let cfg = SequenceConfig { contrast: Contrast::None, velocity_change: change, refine: 0, ..SequenceConfig::default() };
            let mut m = SequenceMatcher::new(&cfg);
            let mut pos = 10.0f64;
            let mut last = None;
            for t in 0..12 {
                pos += if t < 9 { 1.0 } else { 0.0 };
                let p = pos.floor() as u32;
                // the true place, and a weaker neighbour where a straight line would run on
                last = m.push(vec![(place(0, p), 1.0), (place(0, p + 1), 0.25)], &|_| 100);
            }
            (last.unwrap(), pos.floor() as u32)
        };
        let (smooth, truth) = run(0.125);
        assert_eq!(smooth.end, place(0, truth), "{smooth:?}");
        assert!(smooth.velocity <= 0.25, "slowing down at the end: {smooth:?}");
        let (straight, _) = run(1e9);
        assert_ne!(straight.end, place(0, truth), "{straight:?}");
    }

    /// A camera three places a frame on (a stream at a third of the map's frame rate, issue 57):
    /// within 0 to 2 positions a frame no trajectory follows it, and without the newest frame's
    /// support the trajectory left behind is accepted far from the camera; with `support` no
    /// accepted match is; with the range to 4 the camera is followed and accepted where it is.
    #[test]
    fn a_camera_faster_than_the_range_is_never_accepted_behind_itself() {
        let run = |vmax: f64, steps: usize, support: f64| {
            let cfg = SequenceConfig { velocity_max: vmax, velocity_steps: steps, support, ..SequenceConfig::default() };
            let mut m = SequenceMatcher::new(&cfg);
            let (mut wrong, mut right) = (0, 0);
            for t in 0..30u32 {
                let truth = 3 * t;
                // the true place and its neighbours, and two scattered look-alikes
                let mut row =
                    vec![(place(0, truth), 1.0), (place(0, truth + 1), 0.6), (place(0, (t * 37) % 100), 0.7), (place(0, (t * 53 + 11) % 100), 0.5)];
                if truth > 0 {
                    row.push((place(0, truth - 1), 0.6));
                }
                row.sort_by_key(|x| x.0);
                row.dedup_by_key(|x| x.0);
                let row = contributions(&cfg, &row, &|_| 100);
                if let Some(s) = m.push(row, &|_| 100).filter(|s| s.accepted) {
                    match s.place.position.abs_diff(truth) <= 1 {
                        true => right += 1,
                        false => wrong += 1,
                    }
                }
            }
            (wrong, right)
        };
        let (wrong, _) = run(2.0, 9, 0.0);
        assert!(wrong > 0, "the failure of before: accepted behind the camera");
        assert_eq!(run(2.0, 9, 0.5).0, 0, "support: never accepted behind");
        let (wrong, right) = run(4.0, 17, 0.5);
        assert!(wrong == 0 && right >= 15, "followed: {wrong} wrong, {right} right");
    }

    /// One place that scores well against every frame of a moving camera makes a standing
    /// trajectory; it is not accepted, while the same evidence from a camera that stands still
    /// (the same row again and again) is.
    #[test]
    fn a_standing_trajectory_needs_a_camera_that_stands() {
        let cfg = SequenceConfig { contrast: Contrast::None, ..SequenceConfig::default() };
        let run = |moving: bool| {
            let mut m = SequenceMatcher::new(&cfg);
            let mut last = None;
            for t in 0..12u32 {
                // the hub at 50 in every frame; elsewhere a scattered place (moving) or the same
                let other = if moving { (t * 37) % 40 } else { 7 };
                last = m.push(vec![(place(0, 50), 2.0), (place(0, other), 0.5)], &|_| 100);
            }
            last.unwrap()
        };
        let hub = run(true);
        assert_eq!((hub.end, hub.velocity), (place(0, 50), 0.0), "{hub:?}");
        assert!(hub.stillness < 0.95 && !hub.accepted, "{hub:?}");
        let stop = run(false);
        assert_eq!((stop.end, stop.velocity), (place(0, 50), 0.0), "{stop:?}");
        assert!(stop.stillness == 1.0 && stop.accepted, "{stop:?}");
    }

    /// A traversal of 10 places still has competitors for the uniqueness: the window is at most
    /// half the traversal, so a match is not unique by default.
    #[test]
    fn a_short_traversal_keeps_competitors() {
        let cfg = SequenceConfig { contrast: Contrast::None, ..SequenceConfig::default() };
        let mut m = SequenceMatcher::new(&cfg);
        let mut last = None;
        for t in 0..8u32 {
            last = m.push(vec![(place(0, t), 1.0), (place(0, 9), 0.9)], &|_| 10);
        }
        let last = last.unwrap();
        assert_eq!(last.end, place(0, 7));
        assert!(last.uniqueness < UNIQUENESS_CAP && last.uniqueness > 1.0, "{last:?}");
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
