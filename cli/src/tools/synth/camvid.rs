//! A real-label benchmark from CamVid frames under controlled changes: the references are the
//! frames as they are, each query traversal is the same frames under one change, so every query
//! has exactly one correct reference (its own frame) and the real labels follow the frame
//! exactly. Evaluated once with the real labels and once with a segmenter's, it measures the
//! descriptor's quality and the segmenter's apart.
//!
//! Changes (all deterministic):
//! - `night`: gamma 2.2 darkening to 35 % brightness, a blue colour cast, Gaussian noise (sigma 6);
//! - `fog`: a blend towards light grey, denser towards the top of the frame (far away);
//! - `blur`: Gaussian blur, sigma 2.5 px (at CamVid's 480x360);
//! - `shift`: the right 88 % of the frame resized back to full size (a sideways step and zoom);
//!   labels cropped and resized the same way (nearest neighbour).

use image::{GrayImage, RgbImage};
use rayon::prelude::*;
use semlook::dataset::{image_files, DatasetManifest, FrameSpec, TraversalSpec, MANIFEST};
use semlook::error::{Error, Result};
use semlook::input::{LabelFormat, LabelMap};
use semlook::util::SplitMix64;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A controlled change applied to a reference frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Change {
    Night,
    Fog,
    Blur,
    Shift,
}

impl Change {
    pub const ALL: [Change; 4] = [Change::Night, Change::Fog, Change::Blur, Change::Shift];
    pub fn name(self) -> &'static str {
        match self {
            Change::Night => "night",
            Change::Fog => "fog",
            Change::Blur => "blur",
            Change::Shift => "shift",
        }
    }
}

/// Fraction of the width the `shift` change drops on the left.
const SHIFT_CROP: f64 = 0.12;

/// The frame and its labels under `change` (`seed` makes the noise of each frame its own).
pub fn apply(change: Change, rgb: &RgbImage, labels: &GrayImage, seed: u64) -> (RgbImage, GrayImage) {
    let (w, h) = rgb.dimensions();
    match change {
        Change::Night => {
            let mut rng = SplitMix64::new(seed);
            let cast = [0.85f64, 0.95, 1.25];
            let out = RgbImage::from_fn(w, h, |x, y| {
                let p = rgb.get_pixel(x, y).0;
                image::Rgb(std::array::from_fn(|c| {
                    let v = 255.0 * (p[c] as f64 / 255.0).powf(2.2) * 0.35 * cast[c] + 6.0 * rng.normal();
                    v.round().clamp(0.0, 255.0) as u8
                }))
            });
            (out, labels.clone())
        }
        Change::Fog => {
            let out = RgbImage::from_fn(w, h, |x, y| {
                let f = 0.45 + 0.25 * (1.0 - y as f64 / h as f64);
                let p = rgb.get_pixel(x, y).0;
                image::Rgb(std::array::from_fn(|c| (p[c] as f64 * (1.0 - f) + 210.0 * f).round() as u8))
            });
            (out, labels.clone())
        }
        Change::Blur => (image::imageops::blur(rgb, 2.5), labels.clone()),
        Change::Shift => {
            let x0 = (w as f64 * SHIFT_CROP).round() as u32;
            let crop = image::imageops::crop_imm(rgb, x0, 0, w - x0, h).to_image();
            let out = image::imageops::resize(&crop, w, h, image::imageops::FilterType::Triangle);
            // nearest neighbour for labels: source x of output x is x0 + x (w - x0) / w
            let lab = GrayImage::from_fn(w, h, |x, y| {
                let sx = x0 as u64 + ((2 * x as u64 + 1) * (w - x0) as u64) / (2 * w as u64);
                *labels.get_pixel(sx.min(w as u64 - 1) as u32, y)
            });
            (out, lab)
        }
    }
}

/// Writes the benchmark from a CamVid folder (`images/`, `labels/`) into `out`: `reference/`
/// and one folder per change, each with `images/` (JPEG, quality 95) and `labels/` (PNG),
/// and a `semlook-dataset.json` (explicit layout, query i's only valid reference is frame i).
/// `step` keeps every step-th frame. Returns the number of frames per traversal.
pub fn generate(camvid: &Path, out: &Path, changes: &[Change], step: usize, tick: &(dyn Fn() + Sync)) -> Result<usize> {
    let images: Vec<PathBuf> = image_files(&camvid.join("images"))?.into_iter().step_by(step.max(1)).collect();
    if images.is_empty() {
        return Err(Error::dataset(camvid, "no images in images/"));
    }
    let name_of = |p: &Path| p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let traversals: Vec<String> = std::iter::once("reference".to_string()).chain(changes.iter().map(|c| c.name().to_string())).collect();
    for t in &traversals {
        for sub in ["images", "labels"] {
            let d = out.join(t).join(sub);
            std::fs::create_dir_all(&d).map_err(|e| Error::io(&d, e))?;
        }
    }
    images.par_iter().enumerate().try_for_each(|(i, img_path)| -> Result<()> {
        let name = name_of(img_path);
        let label_path = camvid.join("labels").join(format!("{name}.png"));
        let rgb = semlook::input::load_rgb(img_path)?;
        let labels = image::open(&label_path).map_err(|e| Error::ImageDecode { path: label_path.clone(), reason: e.to_string() })?.to_luma8();
        if labels.dimensions() != rgb.dimensions() {
            return Err(Error::SizeMismatch {
                image: img_path.clone(),
                labels: label_path,
                image_size: rgb.dimensions(),
                label_size: labels.dimensions(),
            });
        }
        let write = |t: &str, rgb: &RgbImage, lab: &GrayImage| -> Result<()> {
            let ip = out.join(t).join("images").join(format!("{name}.jpg"));
            let file = std::fs::File::create(&ip).map_err(|e| Error::io(&ip, e))?;
            image::codecs::jpeg::JpegEncoder::new_with_quality(std::io::BufWriter::new(file), 95)
                .encode_image(rgb)
                .map_err(|e| Error::invalid(ip.display().to_string(), e.to_string()))?;
            let lp = out.join(t).join("labels").join(format!("{name}.png"));
            lab.save(&lp).map_err(|e| Error::invalid(lp.display().to_string(), e.to_string()))
        };
        write("reference", &rgb, &labels)?;
        for (k, &c) in changes.iter().enumerate() {
            let (r, l) = apply(c, &rgb, &labels, (i as u64) << 8 | k as u64);
            write(c.name(), &r, &l)?;
        }
        tick();
        Ok(())
    })?;
    let frames = |t: &str, gt: bool| -> Vec<FrameSpec> {
        images
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let n = name_of(p);
                FrameSpec {
                    id: format!("{t}/{n}"),
                    image: Some(PathBuf::from(format!("{t}/images/{n}.jpg"))),
                    labels: Some(PathBuf::from(format!("{t}/labels/{n}.png"))),
                    pose: None,
                    ground_truth: gt.then(|| vec![i as u32]),
                }
            })
            .collect()
    };
    let manifest = DatasetManifest {
        format: "semlook-dataset".into(),
        version: 1,
        name: Some("camvid-changes".into()),
        layout: "explicit".into(),
        camera: None,
        label_format: LabelFormat::Auto,
        label_ids: Some(semlook::config::LabelIds::Named("camvid".into())),
        reference: TraversalSpec::Explicit { name: "reference".into(), frames: frames("reference", false) },
        queries: changes.iter().map(|c| TraversalSpec::Explicit { name: c.name().into(), frames: frames(c.name(), true) }).collect(),
        ground_truth: None,
    };
    let mpath = out.join(MANIFEST);
    std::fs::write(&mpath, serde_json::to_vec_pretty(&manifest).map_err(|e| Error::invalid("dataset manifest", e.to_string()))?)
        .map_err(|e| Error::io(&mpath, e))?;
    Ok(images.len())
}

/// The label map of a CamVid label image under the CamVid class table (for tests and tools).
pub fn camvid_labels(labels: &GrayImage) -> Result<LabelMap> {
    let table = semlook::classes::ClassTable::from_config(&semlook::config::Config::camvid().classes)?;
    semlook::input::decode_label_image(&image::DynamicImage::ImageLuma8(labels.clone()), Path::new("camvid labels"), &table, LabelFormat::Auto)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn changes_keep_labels_aligned() {
        let rgb = RgbImage::from_fn(100, 40, |x, _| image::Rgb([(x * 2) as u8, 100, 200]));
        let labels = GrayImage::from_fn(100, 40, |x, _| image::Luma([if x < 50 { 3 } else { 1 }]));
        for c in Change::ALL {
            let (r, l) = apply(c, &rgb, &labels, 1);
            assert_eq!((r.dimensions(), l.dimensions()), ((100, 40), (100, 40)), "{c:?}");
        }
        // night is darker; the shifted boundary moves left by the crop, scaled back
        let (night, _) = apply(Change::Night, &rgb, &labels, 1);
        assert!(night.get_pixel(50, 20).0[1] < 60);
        let (_, shifted) = apply(Change::Shift, &rgb, &labels, 1);
        let edge = (0..100).find(|&x| shifted.get_pixel(x, 0).0[0] == 1).unwrap();
        assert!((42..=44).contains(&edge), "boundary at {edge}");
        assert!(camvid_labels(&shifted).is_ok());
    }
}
