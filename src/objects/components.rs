//! 8-connected component labelling of same-class pixels: union-find over a raster scan
//! (Rosenfeld & Pfaltz two-pass scheme), with a flood-fill reference beside it for tests.

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

/// Labels 8-connected regions of equal class among pixels whose class is `used`.
pub fn label_components(labels: &LabelMap, used: &[bool; 256]) -> Components {
    let (w, h) = (labels.width() as usize, labels.height() as usize);
    let cls = labels.classes();
    let mut prov = vec![NO_OBJECT; w * h];
    let mut parent: Vec<u32> = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let c = cls[i];
            if !used[c as usize] {
                continue;
            }
            // already-visited 8-neighbours: W, NW, N, NE
            let mut label = NO_OBJECT;
            let mut neighbours = [NO_OBJECT; 4];
            if x > 0 && cls[i - 1] == c {
                neighbours[0] = prov[i - 1];
            }
            if y > 0 {
                let up = i - w;
                if x > 0 && cls[up - 1] == c {
                    neighbours[1] = prov[up - 1];
                }
                if cls[up] == c {
                    neighbours[2] = prov[up];
                }
                if x + 1 < w && cls[up + 1] == c {
                    neighbours[3] = prov[up + 1];
                }
            }
            for n in neighbours.into_iter().filter(|&n| n != NO_OBJECT) {
                if label == NO_OBJECT {
                    label = find(&mut parent, n);
                } else {
                    let (a, b) = (find(&mut parent, label), find(&mut parent, n));
                    if a != b {
                        let (lo, hi) = if a < b { (a, b) } else { (b, a) };
                        parent[hi as usize] = lo;
                        label = lo;
                    }
                }
            }
            if label == NO_OBJECT {
                label = parent.len() as u32;
                parent.push(label);
            }
            prov[i] = label;
        }
    }
    // Roots get dense ids in order of first appearance, which is raster order of first pixels
    // because a root is always the smallest provisional label of its set.
    let mut dense = vec![NO_OBJECT; parent.len()];
    let mut stats: Vec<SemanticObject> = Vec::new();
    let mut sums: Vec<[f64; 2]> = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if prov[i] == NO_OBJECT {
                continue;
            }
            let root = find(&mut parent, prov[i]) as usize;
            if dense[root] == NO_OBJECT {
                dense[root] = stats.len() as u32;
                stats.push(SemanticObject {
                    class: cls[i],
                    area: 0.0,
                    pixel_count: 0,
                    centroid: [0.0; 2],
                    bbox: [x as u32, y as u32, x as u32 + 1, y as u32 + 1],
                });
                sums.push([0.0; 2]);
            }
            let d = dense[root];
            prov[i] = d;
            let s = &mut stats[d as usize];
            s.pixel_count += 1;
            s.bbox = [s.bbox[0].min(x as u32), s.bbox[1], s.bbox[2].max(x as u32 + 1), y as u32 + 1];
            sums[d as usize][0] += x as f64;
            sums[d as usize][1] += y as f64;
        }
    }
    for (s, sum) in stats.iter_mut().zip(&sums) {
        s.area = s.pixel_count as f64;
        s.centroid = [sum[0] / s.area, sum[1] / s.area];
    }
    Components { component_of_pixel: prov, stats }
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
