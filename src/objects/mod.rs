//! Stage 1: label map -> semantic objects (`docs/design/method.md` §2.1).
//!
//! An object is one 8-connected region of one class, i.e. exactly the region enclosed by one
//! outer border of Suzuki & Abe's border following (ref. 25 of the paper; `cv2.findContours` with
//! RETR_EXTERNAL). Regions are found by union-find labelling, which gives each object's pixel
//! count, centroid (image moments m10/m00, m01/m00) and bounding box in one pass; the outer
//! contour itself is traced on demand with imageproc's Suzuki-Abe implementation.

mod components;

pub use components::{label_components, label_components_reference};

use crate::classes::ClassTable;
use crate::config::{AreaMode, ObjectsConfig};
use crate::input::LabelMap;

/// Pixel value of [`ObjectMap::object_of_pixel`] outside every kept object.
pub const NO_OBJECT: u32 = u32::MAX;

/// One semantic object (one tree of the forest to come).
#[derive(Debug, Clone, PartialEq)]
pub struct SemanticObject {
    /// The object's class index in the class table.
    pub class: u8,
    /// Area in pixels, measured as `ObjectsConfig::area` says.
    pub area: f64,
    /// The number of pixels of the region.
    pub pixel_count: u32,
    /// Centroid (x, y) in pixel coordinates, from the region's moments.
    pub centroid: [f64; 2],
    /// Bounding box (x0, y0, x1, y1), x1 and y1 exclusive.
    pub bbox: [u32; 4],
}

/// The objects of one image and which pixel belongs to which.
#[derive(Debug, Clone)]
pub struct ObjectMap {
    /// The label map's width in pixels.
    pub width: u32,
    /// The label map's height in pixels.
    pub height: u32,
    /// The kept objects, in raster order of their first pixel.
    pub objects: Vec<SemanticObject>,
    /// Per pixel, the index of its object in `objects`, or [`NO_OBJECT`].
    pub object_of_pixel: Vec<u32>,
}

/// Extracts the objects of a label map: components of used classes, area filter, at most
/// `max_objects` (largest first), kept in raster order of their first pixel.
pub fn extract_objects(labels: &LabelMap, table: &ClassTable, cfg: &ObjectsConfig) -> ObjectMap {
    let (w, h) = (labels.width(), labels.height());
    let comps = label_components(labels, &table.used_mask());
    let min_area = cfg.min_area_fraction * w as f64 * h as f64;
    let mut stats = comps.stats;
    if cfg.area == AreaMode::Contour {
        for (i, s) in stats.iter_mut().enumerate() {
            let contour = trace_outer_contour(&comps.component_of_pixel, w, i as u32, s.bbox);
            s.area = shoelace_area(&contour);
        }
    }
    // Keep components above the minimum area; if too many, keep the largest (ties: raster order).
    let mut keep: Vec<usize> = (0..stats.len()).filter(|&i| stats[i].area >= min_area && stats[i].area > 0.0).collect();
    if keep.len() > cfg.max_objects {
        keep.sort_by(|&a, &b| stats[b].area.total_cmp(&stats[a].area).then(a.cmp(&b)));
        keep.truncate(cfg.max_objects);
        keep.sort_unstable();
    }
    let mut remap = vec![NO_OBJECT; stats.len()];
    for (new, &old) in keep.iter().enumerate() {
        remap[old] = new as u32;
    }
    let object_of_pixel = comps.component_of_pixel.iter().map(|&c| if c == NO_OBJECT { NO_OBJECT } else { remap[c as usize] }).collect();
    let objects = keep.iter().map(|&i| stats[i].clone()).collect();
    ObjectMap { width: w, height: h, objects, object_of_pixel }
}

impl ObjectMap {
    /// The outer border of object `k` (Suzuki-Abe), as pixel coordinates in tracing order.
    pub fn outer_contour(&self, k: usize) -> Vec<[u32; 2]> {
        trace_outer_contour(&self.object_of_pixel, self.width, k as u32, self.objects[k].bbox)
    }
}

/// Traces the outer border of the region whose pixels carry `id` in `region_of_pixel`, on a crop of
/// its bounding box padded by one background pixel.
fn trace_outer_contour(region_of_pixel: &[u32], width: u32, id: u32, bbox: [u32; 4]) -> Vec<[u32; 2]> {
    let [x0, y0, x1, y1] = bbox;
    let (cw, ch) = (x1 - x0 + 2, y1 - y0 + 2);
    let mut crop = image::GrayImage::new(cw, ch);
    for y in y0..y1 {
        let row = &region_of_pixel[(y * width) as usize..((y + 1) * width) as usize];
        for x in x0..x1 {
            if row[x as usize] == id {
                crop.put_pixel(x - x0 + 1, y - y0 + 1, image::Luma([255]));
            }
        }
    }
    imageproc::contours::find_contours::<i32>(&crop)
        .into_iter()
        .find(|c| c.border_type == imageproc::contours::BorderType::Outer)
        .map(|c| c.points.iter().map(|p| [(p.x - 1) as u32 + x0, (p.y - 1) as u32 + y0]).collect())
        .unwrap_or_default()
}

/// Shoelace area of a closed polygon through pixel centres (cv2.contourArea).
pub fn shoelace_area(points: &[[u32; 2]]) -> f64 {
    let n = points.len();
    let twice: i64 = (0..n)
        .map(|i| {
            let (a, b) = (points[i], points[(i + 1) % n]);
            a[0] as i64 * b[1] as i64 - b[0] as i64 * a[1] as i64
        })
        .sum();
    twice.abs() as f64 / 2.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ObjectsConfig;

    fn map(w: u32, rows: &[&str]) -> LabelMap {
        // '.' = road (0), 'b' = building (2), 'c' = car (13), 'v' = void
        let classes = rows
            .iter()
            .flat_map(|r| r.chars())
            .map(|ch| match ch {
                '.' => 0,
                'b' => 2,
                'c' => 13,
                _ => crate::classes::VOID,
            })
            .collect();
        LabelMap::new(w, rows.len() as u32, classes, &ClassTable::cityscapes()).unwrap()
    }

    #[test]
    fn regions_areas_centroids_and_exclusion() {
        let m = map(6, &["bb..cc", "bb..cc", "....vv", "b....."]);
        let cfg = ObjectsConfig { min_area_fraction: 0.0, ..Default::default() };
        let objs = extract_objects(&m, &ClassTable::cityscapes(), &cfg);
        let summary: Vec<(u8, u32)> = objs.objects.iter().map(|o| (o.class, o.pixel_count)).collect();
        assert_eq!(summary, vec![(2, 4), (0, 13), (13, 4), (2, 1)]);
        assert_eq!(objs.objects[0].centroid, [0.5, 0.5]);
        assert_eq!(objs.objects[2].bbox, [4, 0, 6, 2]);
        let classes = crate::config::ClassesConfig { exclude: vec!["car".into()], ..Default::default() };
        let table = ClassTable::from_config(&classes).unwrap();
        let objs = extract_objects(&m, &table, &cfg);
        assert!(objs.objects.iter().all(|o| o.class != 13));
        assert_eq!(objs.object_of_pixel[4], NO_OBJECT);
    }

    #[test]
    fn min_area_and_max_objects() {
        let m = map(6, &["bb..cc", "bb..cc", "....vv", "b....."]);
        let cfg = ObjectsConfig { min_area_fraction: 2.0 / 24.0, max_objects: 2, ..Default::default() };
        let objs = extract_objects(&m, &ClassTable::cityscapes(), &cfg);
        // single building pixel dropped by area; of the three left, the two largest stay, raster order
        let summary: Vec<(u8, u32)> = objs.objects.iter().map(|o| (o.class, o.pixel_count)).collect();
        assert_eq!(summary, vec![(2, 4), (0, 13)]);
    }

    #[test]
    fn contour_is_the_outer_border() {
        let m = map(5, &[".....", ".bbb.", ".b.b.", ".bbb.", "....."]);
        let cfg = ObjectsConfig { min_area_fraction: 0.0, ..Default::default() };
        let objs = extract_objects(&m, &ClassTable::cityscapes(), &cfg);
        let k = objs.objects.iter().position(|o| o.class == 2).unwrap();
        let mut c = objs.outer_contour(k);
        c.sort();
        assert_eq!(c, vec![[1, 1], [1, 2], [1, 3], [2, 1], [2, 3], [3, 1], [3, 2], [3, 3]]);
        assert_eq!(shoelace_area(&objs.outer_contour(k)), 4.0);
        let cfg = ObjectsConfig { min_area_fraction: 0.0, area: AreaMode::Contour, ..Default::default() };
        let objs = extract_objects(&m, &ClassTable::cityscapes(), &cfg);
        assert_eq!(objs.objects.iter().find(|o| o.class == 2).unwrap().area, 4.0);
    }
}
