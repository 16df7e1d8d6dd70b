//! 8-connected component labelling of same-class pixels: union-find over row runs (a run-based
//! variant of the Rosenfeld & Pfaltz two-pass scheme), with a flood-fill reference beside it.

use super::{SemanticObject, NO_OBJECT};
use crate::input::LabelMap;

/// Components in raster order of their first pixel, with per-pixel component ids.
pub struct Components {
    pub component_of_pixel: Vec<u32>,
    pub stats: Vec<SemanticObject>,
}

fn find(parent: &mut [u32], mut x: u32) -> u32 {
    while parent[x as usize] != x {
        let p = parent[x as usize];
        parent[x as usize] = parent[p as usize];
        x = p;
    }
    x
}

/// A horizontal run of equal class in one row: pixels [x0, x1) of row y.
struct Run {
    y: u32,
    x0: u32,
    x1: u32,
    class: u8,
}

/// Labels 8-connected regions of equal class among pixels whose class is `used`.
///
/// Run-based: each row is cut into runs of equal class, and a run is united with the runs of
/// the same class in the previous row that touch it 8-connectedly (overlap widened by one pixel).
/// Statistics are summed per run, so the per-pixel work is one pass to find runs and one fill.
pub fn label_components(labels: &LabelMap, used: &[bool; 256]) -> Components {
    let (w, h) = (labels.width() as usize, labels.height() as usize);
    let cls = labels.classes();
    let mut runs: Vec<Run> = Vec::new();
    let mut parent: Vec<u32> = Vec::new();
    let mut prev_start = 0usize; // runs of the previous row: prev_start..row_start
    for y in 0..h {
        let row = &cls[y * w..(y + 1) * w];
        let row_start = runs.len();
        let mut x = 0;
        while x < w {
            let c = row[x];
            let x0 = x;
            while x < w && row[x] == c {
                x += 1;
            }
            if used[c as usize] {
                runs.push(Run { y: y as u32, x0: x0 as u32, x1: x as u32, class: c });
                parent.push((runs.len() - 1) as u32);
            }
        }
        // unite with touching runs of the previous row (both lists sorted by x)
        let mut j = prev_start;
        for i in row_start..runs.len() {
            let (x0, x1, c) = (runs[i].x0, runs[i].x1, runs[i].class);
            while j < row_start && runs[j].x1 < x0 {
                j += 1; // ends more than one pixel left of this run
            }
            let mut k = j;
            while k < row_start && runs[k].x0 <= x1 {
                if runs[k].class == c {
                    let (a, b) = (find(&mut parent, i as u32), find(&mut parent, k as u32));
                    if a != b {
                        let (lo, hi) = if a < b { (a, b) } else { (b, a) };
                        parent[hi as usize] = lo;
                    }
                }
                k += 1;
            }
        }
        prev_start = row_start;
    }
    // Dense ids in order of first run, i.e. raster order of first pixels.
    let mut dense = vec![NO_OBJECT; runs.len()];
    let mut stats: Vec<SemanticObject> = Vec::new();
    let mut sums: Vec<[f64; 2]> = Vec::new();
    let mut component_of_pixel = vec![NO_OBJECT; w * h];
    for (i, r) in runs.iter().enumerate() {
        let root = find(&mut parent, i as u32) as usize;
        if dense[root] == NO_OBJECT {
            dense[root] = stats.len() as u32;
            stats.push(SemanticObject { class: r.class, area: 0.0, pixel_count: 0, centroid: [0.0; 2], bbox: [r.x0, r.y, r.x1, r.y + 1] });
            sums.push([0.0; 2]);
        }
        let d = dense[root];
        let n = r.x1 - r.x0;
        let s = &mut stats[d as usize];
        s.pixel_count += n;
        s.bbox = [s.bbox[0].min(r.x0), s.bbox[1], s.bbox[2].max(r.x1), r.y + 1];
        // sum of x over the run, and of y
        sums[d as usize][0] += (r.x0 + r.x1 - 1) as f64 * n as f64 / 2.0;
        sums[d as usize][1] += r.y as f64 * n as f64;
        let base = r.y as usize * w;
        component_of_pixel[base + r.x0 as usize..base + r.x1 as usize].fill(d);
    }
    for (s, sum) in stats.iter_mut().zip(&sums) {
        s.area = s.pixel_count as f64;
        s.centroid = [sum[0] / s.area, sum[1] / s.area];
    }
    Components { component_of_pixel, stats }
}

/// Brute-force reference: breadth-first flood fill from each unvisited pixel in raster order.
pub fn label_components_reference(labels: &LabelMap, used: &[bool; 256]) -> Components {
    let (w, h) = (labels.width() as i64, labels.height() as i64);
    let cls = labels.classes();
    let mut comp = vec![NO_OBJECT; (w * h) as usize];
    let mut stats = Vec::new();
    for start in 0..(w * h) {
        let c = cls[start as usize];
        if !used[c as usize] || comp[start as usize] != NO_OBJECT {
            continue;
        }
        let id = stats.len() as u32;
        let mut queue = std::collections::VecDeque::from([start]);
        comp[start as usize] = id;
        let (mut n, mut sx, mut sy) = (0u32, 0f64, 0f64);
        let mut bbox = [u32::MAX, u32::MAX, 0, 0];
        while let Some(p) = queue.pop_front() {
            let (x, y) = (p % w, p / w);
            n += 1;
            sx += x as f64;
            sy += y as f64;
            bbox = [bbox[0].min(x as u32), bbox[1].min(y as u32), bbox[2].max(x as u32 + 1), bbox[3].max(y as u32 + 1)];
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (nx, ny) = (x + dx, y + dy);
                    if nx < 0 || ny < 0 || nx >= w || ny >= h {
                        continue;
                    }
                    let q = (ny * w + nx) as usize;
                    if cls[q] == c && comp[q] == NO_OBJECT {
                        comp[q] = id;
                        queue.push_back(q as i64);
                    }
                }
            }
        }
        stats.push(SemanticObject { class: c, area: n as f64, pixel_count: n, centroid: [sx / n as f64, sy / n as f64], bbox });
    }
    Components { component_of_pixel: comp, stats }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::classes::ClassTable;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        /// Run-based labelling equals flood fill: same components, order, ids and statistics.
        #[test]
        fn equals_flood_fill(w in 1u32..30, h in 1u32..30, k in 1u8..5, seed in any::<u64>()) {
            let t = ClassTable::cityscapes();
            let mut rng = crate::util::SplitMix64::new(seed);
            // few classes and void, so regions touch, nest and wrap around
            let c: Vec<u8> = (0..w * h).map(|_| { let v = rng.below(k as usize + 1) as u8; if v == k { crate::classes::VOID } else { v } }).collect();
            let m = LabelMap::new(w, h, c, &t).unwrap();
            let mut used = t.used_mask();
            used[1] = seed % 3 != 0; // sometimes a class is excluded
            let fast = label_components(&m, &used);
            let slow = label_components_reference(&m, &used);
            prop_assert_eq!(&fast.component_of_pixel, &slow.component_of_pixel);
            prop_assert_eq!(&fast.stats, &slow.stats);
        }
    }
}
