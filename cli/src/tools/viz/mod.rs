//! Pictures of what the engine sees: `inspect` (every stage of one frame), `explain` (the worst
//! queries of an evaluation: query | top-1 | a valid reference), precision-recall and recall@N
//! charts, and the HTML report of an evaluation ([`report`]).
//! Text on raster pictures uses a built-in bitmap font ([`font`]); the SVG plots carry real text.

pub mod font;
pub mod plots;
pub mod report;

use image::{Rgb, RgbImage};
use semlook::appearance::keypoints::Keypoints;
use semlook::classes::ClassTable;
use semlook::encode::Encoder;
use semlook::error::{Error, Result};
use semlook::input::{FrameSource, LabelFormat, LabelMap};
use semlook::local::Forest;
use semlook::objects::{ObjectMap, NO_OBJECT};
use std::path::Path;

/// A picture and its title.
pub type Panel = (String, RgbImage);

/// Draws a line with Bresenham's algorithm (clipped to the image).
pub fn line(img: &mut RgbImage, (x0, y0): (i64, i64), (x1, y1): (i64, i64), c: Rgb<u8>) {
    let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
    let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
    let (mut x, mut y, mut err) = (x0, y0, dx + dy);
    loop {
        put(img, x, y, c);
        if x == x1 && y == y1 {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x += sx;
        }
        if e2 <= dx {
            err += dx;
            y += sy;
        }
    }
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, c);
    }
}

/// A filled disk of radius `r`.
pub fn disk(img: &mut RgbImage, cx: i64, cy: i64, r: i64, c: Rgb<u8>) {
    for y in -r..=r {
        for x in -r..=r {
            if x * x + y * y <= r * r {
                put(img, cx + x, cy + y, c);
            }
        }
    }
}

/// Text on a dark box, top-left at (x, y).
pub fn label(img: &mut RgbImage, x: i64, y: i64, text: &str, scale: u32, c: Rgb<u8>) {
    let (w, h) = (font::width(text, scale) as i64 + 2, (font::LINE * scale) as i64);
    for yy in y..y + h {
        for xx in x..x + w {
            put(img, xx, yy, Rgb([0, 0, 0]));
        }
    }
    font::render(text, x + 1, y + 1, scale, |px, py| put(img, px, py, c));
}

/// A label map in the class table's palette (void black).
pub fn labels_image(labels: &LabelMap, table: &ClassTable) -> RgbImage {
    RgbImage::from_fn(labels.width(), labels.height(), |x, y| Rgb(table.color(labels.get(x, y))))
}

/// A 0/1 map (edges) as white on black.
pub fn mask_image(values: &[u32], w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| if values[(y * w + x) as usize] != 0 { Rgb([255, 255, 255]) } else { Rgb([0, 0, 0]) })
}

/// Squared distances as grey, truncated at `tau` (white = at or beyond tau).
pub fn distance_image(d2: &[u32], w: u32, h: u32, tau: f32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| {
        let v = ((d2[(y * w + x) as usize] as f32).sqrt() / tau).min(1.0);
        let g = (v * 255.0).round() as u8;
        Rgb([g, g, g])
    })
}

/// The global descriptor (values in [0, 1]) as grey, each cell `scale` x `scale` pixels.
pub fn descriptor_image(desc: &[f32], gw: u32, gh: u32, scale: u32) -> RgbImage {
    RgbImage::from_fn(gw * scale, gh * scale, |x, y| {
        let g = (desc[((y / scale) * gw + x / scale) as usize].clamp(0.0, 1.0) * 255.0).round() as u8;
        Rgb([g, g, g])
    })
}

fn blend(a: Rgb<u8>, b: Rgb<u8>, t: f32) -> Rgb<u8> {
    Rgb(std::array::from_fn(|i| (a.0[i] as f32 * (1.0 - t) + b.0[i] as f32 * t).round() as u8))
}

/// Objects in their class colours over the darkened image, outlined; each tree's id at its
/// centroid and a line to each of its neighbours.
pub fn objects_image(base: &RgbImage, objects: &ObjectMap, forest: &Forest, labels: &LabelMap, table: &ClassTable) -> RgbImage {
    let (w, h) = (objects.width, objects.height);
    let mut img = RgbImage::from_fn(w, h, |x, y| {
        let o = objects.object_of_pixel[(y * w + x) as usize];
        let px = *base.get_pixel(x.min(base.width() - 1), y.min(base.height() - 1));
        if o == NO_OBJECT {
            blend(px, Rgb([0, 0, 0]), 0.7)
        } else {
            blend(px, Rgb(table.color(labels.get(x, y))), 0.6)
        }
    });
    // outlines: pixels whose right or lower neighbour belongs to another object
    for y in 0..h {
        for x in 0..w {
            let o = objects.object_of_pixel[(y * w + x) as usize];
            let right = if x + 1 < w { objects.object_of_pixel[(y * w + x + 1) as usize] } else { o };
            let down = if y + 1 < h { objects.object_of_pixel[((y + 1) * w + x) as usize] } else { o };
            if o != right || o != down {
                img.put_pixel(x, y, Rgb([255, 255, 255]));
            }
        }
    }
    let diag = ((w as f64).powi(2) + (h as f64).powi(2)).sqrt();
    let at = |k: usize| ((forest.centroids[2 * k] as f64 * diag) as i64, (forest.centroids[2 * k + 1] as f64 * diag) as i64);
    for k in 0..forest.len() {
        for j in forest.neighbours_of(k) {
            line(&mut img, at(k), at(j), Rgb([255, 230, 0]));
        }
    }
    for k in 0..forest.len() {
        let (x, y) = at(k);
        disk(&mut img, x, y, 2, Rgb([255, 230, 0]));
        label(&mut img, x + 3, y - 4, &k.to_string(), 1, Rgb([255, 255, 255]));
    }
    img
}

/// Keypoints (or dense cells) as dots, coloured by the class of the object they fall in (grey
/// outside every object).
pub fn keypoints_image(base: &RgbImage, k: &Keypoints, objects: &ObjectMap, labels: &LabelMap, table: &ClassTable) -> RgbImage {
    let mut img = RgbImage::from_fn(base.width(), base.height(), |x, y| blend(*base.get_pixel(x, y), Rgb([0, 0, 0]), 0.4));
    for p in &k.xy {
        let (x, y) = ((p[0].round() as i64).clamp(0, objects.width as i64 - 1), (p[1].round() as i64).clamp(0, objects.height as i64 - 1));
        let o = objects.object_of_pixel[(y as u32 * objects.width + x as u32) as usize];
        let c = if o == NO_OBJECT { Rgb([160, 160, 160]) } else { Rgb(table.color(labels.get(x as u32, y as u32))) };
        disk(&mut img, x, y, 1, c);
    }
    img
}

/// Every stage of one frame, as titled panels: image, labels, semantic edges, truncated EDT,
/// global descriptor, objects with trees and neighbour links, keypoints.
pub fn inspect(encoder: &Encoder, src: &FrameSource, format: LabelFormat) -> Result<Vec<Panel>> {
    let loaded = encoder.frames().load(src, format)?;
    let cfg = encoder.config();
    let table = encoder.class_table();
    let labels = &loaded.labels;
    let (w, h) = (labels.width(), labels.height());
    let p = encoder.global().ssim_params();
    let (mut desc, mut stats) = (vec![0.0; p.len()], vec![0.0; p.stats_len()]);
    let mut scratch = semlook::global::GlobalScratch::default();
    semlook::global::encode_global(labels, encoder.global().used_mask(), &cfg.global, &mut scratch, &mut desc, &mut stats)?;
    let tau = semlook::global::pool_params(&cfg.global, w, h).tau;
    let objects = semlook::objects::extract_objects(labels, table, &cfg.objects);
    let forest = semlook::local::build_forest(&objects, &cfg.local);
    let base = match &loaded.rgb {
        Some(rgb) => rgb.clone(),
        None => match &src.image {
            Some(p) => semlook::input::resize_rgb(&semlook::input::load_rgb(p)?, w, h),
            None => labels_image(labels, table),
        },
    };
    let scale = (512 / cfg.global.width.max(1)).max(1) as u32;
    let mut panels = vec![
        (format!("image {}x{} (working size)", w, h), base.clone()),
        ("labels".to_string(), labels_image(labels, table)),
        ("semantic edges".to_string(), mask_image(scratch.edges(), w, h)),
        (format!("EDT truncated at {tau:.0} px"), distance_image(scratch.d2(), w, h, tau)),
        (
            format!("global descriptor {}x{}", cfg.global.width, cfg.global.height),
            descriptor_image(&desc, cfg.global.width as u32, cfg.global.height as u32, scale),
        ),
        (format!("{} trees and neighbour links", forest.len()), objects_image(&base, &objects, &forest, labels, table)),
    ];
    if let (Some(model), Some(rgb)) = (encoder.appearance_model(), &loaded.rgb) {
        let k = model.keypoints(rgb)?;
        panels.push((format!("{} appearance descriptors", k.len()), keypoints_image(rgb, &k, &objects, labels, table)));
    }
    Ok(panels)
}

/// Panels side by side in rows of `columns`, each under its title, scaled to `cell_width`.
pub fn sheet(panels: &[Panel], columns: usize, cell_width: u32) -> RgbImage {
    let columns = columns.max(1);
    let fit = |img: &RgbImage| -> RgbImage {
        let hh = ((img.height() as f64 * cell_width as f64 / img.width().max(1) as f64).round() as u32).max(1);
        image::imageops::resize(img, cell_width, hh, image::imageops::FilterType::Nearest)
    };
    let scaled: Vec<(String, RgbImage)> = panels.iter().map(|(t, i)| (t.clone(), fit(i))).collect();
    let title_h = font::LINE * 2 + 4;
    let rows: Vec<&[(String, RgbImage)]> = scaled.chunks(columns).collect();
    let row_h: Vec<u32> = rows.iter().map(|r| r.iter().map(|p| p.1.height()).max().unwrap_or(0) + title_h).collect();
    let mut out = RgbImage::from_pixel(
        cell_width * columns as u32 + 4 * (columns as u32 + 1),
        row_h.iter().sum::<u32>() + 4 * (rows.len() as u32 + 1),
        Rgb([32, 32, 32]),
    );
    let mut y = 4;
    for (r, row) in rows.iter().enumerate() {
        for (c, (title, img)) in row.iter().enumerate() {
            let x = 4 + c as u32 * (cell_width + 4);
            label(&mut out, x as i64, y as i64, title, 2, Rgb([255, 255, 255]));
            image::imageops::replace(&mut out, img, x as i64, (y + title_h) as i64);
        }
        y += row_h[r] + 4;
    }
    out
}

/// Writes panels as `<n>-<slug>.png` files and a `sheet.png` of all of them into `dir`.
pub fn write_panels(panels: &[Panel], dir: &Path) -> Result<Vec<std::path::PathBuf>> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut written = Vec::new();
    for (i, (title, img)) in panels.iter().enumerate() {
        let slug: String =
            title.split(' ').take(2).collect::<Vec<_>>().join("-").chars().filter(|c| c.is_ascii_alphanumeric() || *c == '-').collect();
        let p = dir.join(format!("{i}-{slug}.png"));
        save(img, &p)?;
        written.push(p);
    }
    let p = dir.join("sheet.png");
    save(&sheet(panels, 4, 480), &p)?;
    written.push(p);
    Ok(written)
}

pub fn save(img: &RgbImage, path: &Path) -> Result<()> {
    img.save(path).map_err(|e| Error::invalid(path.display().to_string(), e.to_string()))
}

/// One column of an explain sheet: a frame's image and labels under a caption (the image alone
/// for a frame encoded without labels), `width` pixels wide: the image and labels are scaled to
/// it (nearest neighbour) before the caption is drawn, so that a caption stays whole and legible
/// on frames of any size (a 64x32 frame's column is no longer 64 pixels of clipped text scaled up).
pub fn frame_column(encoder: &Encoder, src: &FrameSource, format: LabelFormat, caption: &[String], width: u32) -> Result<Panel> {
    let loaded = encoder.frames().load(src, format)?;
    let table = encoder.class_table();
    let (w, h) = (loaded.labels.width(), loaded.labels.height());
    let base = match (&loaded.rgb, &src.image) {
        (Some(rgb), _) => rgb.clone(),
        (None, Some(p)) => semlook::input::resize_rgb(&semlook::input::load_rgb(p)?, w, h),
        (None, None) => RgbImage::new(w, h),
    };
    let labelled = loaded.labels.classes().iter().any(|&c| c != semlook::classes::VOID);
    let labels = labelled.then(|| labels_image(&loaded.labels, table));
    let col = captioned(&base, labels.as_ref(), caption, width);
    Ok((src.id.clone(), col))
}

/// `base` (and `labels` under it) scaled to `width` pixels (nearest neighbour) under `caption`,
/// one line of text a line: the caption drawn after the scaling, so it stays whole on a frame
/// narrower than its text.
fn captioned(base: &RgbImage, labels: Option<&RgbImage>, caption: &[String], width: u32) -> RgbImage {
    let width = width.max(1);
    let height = ((base.height() as f64 * width as f64 / base.width().max(1) as f64).round() as u32).max(1);
    let fit = |img: &RgbImage| image::imageops::resize(img, width, height, image::imageops::FilterType::Nearest);
    let text_h = (caption.len() as u32) * font::LINE * 2 + 4;
    let mut col = RgbImage::from_pixel(width, if labels.is_some() { 2 } else { 1 } * height + text_h, Rgb([32, 32, 32]));
    for (i, line) in caption.iter().enumerate() {
        label(&mut col, 2, 2 + (i as u32 * font::LINE * 2) as i64, line, 2, Rgb([255, 255, 255]));
    }
    image::imageops::replace(&mut col, &fit(base), 0, text_h as i64);
    if let Some(l) = labels {
        image::imageops::replace(&mut col, &fit(l), 0, (text_h + height) as i64);
    }
    col
}

/// The worst queries of an evaluation, worst first: wrong top-1s, most confident first, then
/// the least confident correct ones (queries without ground truth left out).
pub fn worst_queries(report: &semlook::eval::EvalReport, setting: semlook::matching::Setting) -> Vec<(&str, &semlook::eval::QueryOutcome)> {
    let mut worst: Vec<(&str, &semlook::eval::QueryOutcome)> = report
        .results
        .iter()
        .filter(|r| r.setting == setting)
        .flat_map(|r| r.outcomes.iter().filter(|o| o.valid_references > 0).map(move |o| (r.query_set.as_str(), o)))
        .collect();
    let key = |o: &semlook::eval::QueryOutcome| {
        let s = o.score.unwrap_or(f32::NEG_INFINITY) as f64;
        if o.correct {
            (1, s)
        } else {
            (0, -s)
        }
    };
    worst.sort_by(|a, b| key(a.1).partial_cmp(&key(b.1)).unwrap_or(std::cmp::Ordering::Equal));
    worst
}

/// A sheet of one of the worst queries: query | top-1 | a valid reference, each column's image
/// and labels under its caption, `cell_width` pixels wide.
pub fn worst_sheet(
    (set, o): (&str, &semlook::eval::QueryOutcome),
    setting: semlook::matching::Setting,
    ds: &semlook::dataset::Dataset,
    encoder: &Encoder,
    cell_width: u32,
) -> Result<RgbImage> {
    // by id, else (a reference named by the map: `09` for the dataset's `ref/09.jpg`) by the
    // file stem where exactly one reference frame has it, as eval resolves the map's images
    let find = |id: &str| {
        let all = || std::iter::once(&ds.reference).chain(&ds.queries).flat_map(|t| &t.frames);
        if let Some(f) = all().find(|f| f.source.id == id) {
            return Ok(&f.source);
        }
        let stem = semlook::eval::id_stem(id);
        let mut same = ds.reference.frames.iter().filter(|f| stem.is_some() && semlook::eval::id_stem(&f.source.id) == stem);
        match (same.next(), same.next()) {
            (Some(f), None) => Ok(&f.source),
            _ => Err(Error::dataset(&ds.root, format!("frame {id:?} of the report is not in the dataset"))),
        }
    };
    let mut cols =
        vec![frame_column(encoder, find(&o.query)?, ds.label_format, &[format!("query {}", o.query), format!("set {set}, {setting}")], cell_width)?];
    if let Some(top) = &o.top1 {
        let verdict = if o.correct { "correct" } else { "wrong" };
        let caption = [format!("top-1 {top} ({verdict})"), format!("score {:.3}", o.score.unwrap_or(f32::NAN))];
        cols.push(frame_column(encoder, find(top)?, ds.label_format, &caption, cell_width)?);
    }
    let valid = o
        .best_valid
        .as_ref()
        .map(|(id, rank)| (id.clone(), format!("rank {}", rank + 1)))
        .or_else(|| o.a_valid_reference.clone().map(|id| (id, "not in the ranked list".into())));
    if let Some((id, rank)) = valid {
        cols.push(frame_column(encoder, find(&id)?, ds.label_format, &[format!("valid {id}"), rank], cell_width)?);
    }
    Ok(sheet(&cols, 3, cell_width))
}

/// For the `n` worst queries of `setting` in `report` ([`worst_queries`]), a sheet per query
/// ([`worst_sheet`]) written to `dir` as `explain-NN.png`. Frames are found by id in `ds`.
pub fn explain(
    report: &semlook::eval::EvalReport,
    setting: semlook::matching::Setting,
    ds: &semlook::dataset::Dataset,
    encoder: &Encoder,
    n: usize,
    dir: &Path,
) -> Result<Vec<std::path::PathBuf>> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut written = Vec::new();
    for (i, w) in worst_queries(report, setting).into_iter().take(n).enumerate() {
        let p = dir.join(format!("explain-{:02}.png", i + 1));
        save(&worst_sheet(w, setting, ds, encoder, 480)?, &p)?;
        written.push(p);
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An explain sheet's column of a 64x32 frame: the frame scaled to the column's width and
    /// its caption drawn at that width, whole (before, the caption was clipped to the frame's 64
    /// pixels and then scaled up with it, unreadable).
    #[test]
    fn a_small_frames_caption_is_drawn_whole_at_the_columns_width() {
        let base = RgbImage::from_pixel(64, 32, Rgb([0, 0, 128]));
        let labels = RgbImage::from_pixel(64, 32, Rgb([0, 128, 0]));
        let caption = ["top-1 ref/031.png (wrong)".to_string(), "score 4.542".to_string()];
        let col = captioned(&base, Some(&labels), &caption, 480);
        let text_h = 2 * font::LINE * 2 + 4;
        assert_eq!((col.width(), col.height()), (480, text_h + 2 * 240));
        // the caption's white pixels reach as far as its text at scale 2, far beyond 64 pixels,
        // and are drawn at that scale (no stroke wider than 2 x the font's)
        let white: Vec<u32> = (0..text_h)
            .flat_map(|y| (0..480).map(move |x| (x, y)))
            .filter(|&(x, y)| col.get_pixel(x, y).0 == [255, 255, 255])
            .map(|(x, _)| x)
            .collect();
        let right = *white.iter().max().unwrap();
        assert!(right as i64 >= font::width(&caption[0], 2) as i64 - 4 && right > 200, "caption ends at {right}");
        // the frame and its labels below, scaled whole
        assert_eq!(col.get_pixel(479, text_h).0, [0, 0, 128]);
        assert_eq!(col.get_pixel(479, text_h + 479 / 2).0, [0, 0, 128]);
        assert_eq!(col.get_pixel(0, text_h + 240).0, [0, 128, 0]);
        assert_eq!(col.get_pixel(479, text_h + 479).0, [0, 128, 0]);
    }
}
