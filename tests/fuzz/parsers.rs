//! Targets for the file parsers: label maps, images, datasets, ground truth, poses, config and
//! the pickle machine.

use crate::mutate::{crc32, png_fixup, random_seeds, Entropy};
use crate::{Target, Verdict};
use image::{DynamicImage, GrayImage, ImageFormat, Luma, LumaA, Rgb, RgbImage, Rgba, RgbaImage};
use semlook::classes::{ClassTable, CITYSCAPES};
use semlook::config::Config;
use semlook::dataset::{Dataset, DatasetOptions, PoseFormat};
use semlook::input::LabelFormat;
use semlook::Error;
use std::path::{Path, PathBuf};

fn encode(img: DynamicImage, format: ImageFormat) -> Vec<u8> {
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), format).expect("a seed image encodes");
    out
}

/// A 16 x 12 map of Cityscapes train ids (and void) in stripes.
fn id_at(x: u32, y: u32) -> u8 {
    if (x + y).is_multiple_of(7) {
        255
    } else {
        ((x / 3 + y / 4) % 19) as u8
    }
}

fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let start = out.len();
    out.extend_from_slice(kind);
    out.extend_from_slice(data);
    let crc = crc32(&out[start..]);
    out.extend_from_slice(&crc.to_be_bytes());
}

/// An indexed-colour PNG (colour type 3) whose palette is the Cityscapes one: written by hand,
/// as the image crate writes no palette files; zlib with stored blocks.
fn indexed_png(w: u32, h: u32) -> Vec<u8> {
    let mut raw = Vec::new();
    for y in 0..h {
        raw.push(0); // filter: none
        raw.extend((0..w).map(|x| id_at(x, y) % 19));
    }
    let mut z = vec![0x78, 0x01];
    for (i, block) in raw.chunks(65535).enumerate() {
        let last = (i + 1) * 65535 >= raw.len();
        z.push(last as u8);
        z.extend_from_slice(&(block.len() as u16).to_le_bytes());
        z.extend_from_slice(&(!(block.len() as u16)).to_le_bytes());
        z.extend_from_slice(block);
    }
    let (mut a, mut b) = (1u32, 0u32);
    for &v in &raw {
        a = (a + v as u32) % 65521;
        b = (b + a) % 65521;
    }
    z.extend_from_slice(&((b << 16) | a).to_be_bytes());
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = w.to_be_bytes().to_vec();
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 3, 0, 0, 0]);
    chunk(&mut out, b"IHDR", &ihdr);
    let plte: Vec<u8> = CITYSCAPES.iter().flat_map(|c| c.1).collect();
    chunk(&mut out, b"PLTE", &plte);
    chunk(&mut out, b"IDAT", &z);
    chunk(&mut out, b"IEND", &[]);
    out
}

fn label_kind(e: &Error) -> bool {
    matches!(
        e,
        Error::ImageDecode { .. }
            | Error::EmptyImage { .. }
            | Error::UnknownClassId { .. }
            | Error::UnknownClassColor { .. }
            | Error::UnsupportedLabelFormat { .. }
            | Error::Io { .. }
    )
}

/// Decodes `bytes` as a label map in each of `formats`; an accepted map is encoded too.
fn label_run(bytes: &[u8], name: &str, formats: &[LabelFormat]) -> Verdict {
    let table = ClassTable::cityscapes();
    let mut accepted = false;
    for &f in formats {
        match semlook::input::decode_label_bytes(bytes.to_vec(), Path::new(name), &table, f) {
            Ok(map) => {
                accepted = true;
                let cfg = Config::without_appearance();
                let enc = match semlook::encode::Encoder::new(&cfg) {
                    Ok(e) => e,
                    Err(e) => return Verdict::Violation(format!("encoder: {e}")),
                };
                if let Err(e) = enc.encode_labels("fuzz", &map, &mut Default::default()) {
                    return Verdict::Violation(format!("a decoded label map does not encode: {e}"));
                }
            }
            Err(e) => {
                if let v @ Verdict::Violation(_) = Verdict::refused(&e, name, label_kind) {
                    return v;
                }
            }
        }
    }
    if accepted {
        Verdict::Accepted
    } else {
        Verdict::Refused
    }
}

pub fn label_png_grey() -> Option<Target> {
    let grey = GrayImage::from_fn(16, 12, |x, y| Luma([id_at(x, y)]));
    let wide = image::ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(16, 12, |x, y| Luma([id_at(x, y) as u16]));
    let alpha = image::ImageBuffer::<LumaA<u8>, Vec<u8>>::from_fn(9, 5, |x, y| LumaA([id_at(x, y), 255]));
    let seeds = vec![
        encode(DynamicImage::ImageLuma8(grey), ImageFormat::Png),
        encode(DynamicImage::ImageLuma16(wide), ImageFormat::Png),
        encode(DynamicImage::ImageLumaA8(alpha), ImageFormat::Png),
    ];
    let formats = [LabelFormat::Auto, LabelFormat::FirstChannel];
    Some(Target {
        name: "label_png_grey",
        seeds,
        fixup: Some(png_fixup),
        quick: 400,
        run: Box::new(move |b| label_run(b, "fuzz/grey.png", &formats)),
    })
}

pub fn label_png_palette() -> Option<Target> {
    let colour = |x, y| CITYSCAPES[(id_at(x, y) % 19) as usize].1;
    let rgb = RgbImage::from_fn(16, 12, |x, y| Rgb(colour(x, y)));
    let rgba = RgbaImage::from_fn(7, 6, |x, y| {
        let c = colour(x, y);
        Rgba([c[0], c[1], c[2], 255])
    });
    let seeds =
        vec![encode(DynamicImage::ImageRgb8(rgb), ImageFormat::Png), encode(DynamicImage::ImageRgba8(rgba), ImageFormat::Png), indexed_png(16, 12)];
    let formats = [LabelFormat::Auto, LabelFormat::Palette, LabelFormat::FirstChannel];
    Some(Target {
        name: "label_png_palette",
        seeds,
        fixup: Some(png_fixup),
        quick: 400,
        run: Box::new(move |b| label_run(b, "fuzz/palette.png", &formats)),
    })
}

pub fn rgb_image() -> Option<Target> {
    let img = RgbImage::from_fn(48, 40, |x, y| Rgb([(x * 5) as u8, (y * 6) as u8, ((x ^ y) * 9) as u8]));
    let grey = GrayImage::from_fn(40, 33, |x, y| Luma([(x * y) as u8]));
    let seeds = vec![
        encode(DynamicImage::ImageRgb8(img.clone()), ImageFormat::Jpeg),
        encode(DynamicImage::ImageLuma8(grey), ImageFormat::Jpeg),
        encode(DynamicImage::ImageRgb8(img), ImageFormat::Png),
    ];
    let name = "fuzz/frame.jpg";
    let typed = |e: &Error| matches!(e, Error::ImageDecode { .. } | Error::EmptyImage { .. } | Error::Io { .. });
    let run = move |b: &[u8]| {
        let mut verdict = Verdict::Refused;
        for half in [false, true] {
            let r = semlook::input::decode_rgb_at_least(b.to_vec(), Path::new(name), |(w, h)| if half { (w / 2 + 1, h / 3 + 1) } else { (w, h) });
            match r {
                Ok((img, _)) => {
                    verdict = Verdict::Accepted;
                    // the keypoint network's input: a typed refusal below 32 x 32
                    if let Err(e) = semlook::networks::network_input(&img) {
                        if !matches!(e, Error::InvalidInput { .. }) {
                            return Verdict::Violation(format!("network input: {e:?}"));
                        }
                    }
                }
                Err(e) => {
                    if let v @ Verdict::Violation(_) = Verdict::refused(&e, name, typed) {
                        return v;
                    }
                }
            }
        }
        verdict
    };
    Some(Target { name: "rgb_image", seeds, fixup: None, quick: 300, run: Box::new(run) })
}

fn touch(path: &Path, text: &str) {
    std::fs::create_dir_all(path.parent().expect("a parent")).expect("fixture folder");
    std::fs::write(path, text).expect("fixture file");
}

/// Datasets only list image files (decoding comes later): empty files suffice.
fn dataset_root() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().expect("temp dir");
    let root = dir.path().to_path_buf();
    let pose = "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n";
    for t in ["day", "night"] {
        for f in ["000000", "000001"] {
            touch(&root.join(format!("{t}/RGB/Stereo_Left/Omni_F/{f}.png")), "");
            touch(&root.join(format!("{t}/CameraParams/Stereo_Left/Omni_F/{f}.txt")), pose);
        }
    }
    for f in ["db/a.png", "db/b.png", "q/c.png"] {
        touch(&root.join("imgs").join(f), "");
    }
    touch(&root.join("imgs/poses.txt"), "a.png 1 0 0 0 0 0 0\nb.png 1 0 0 0 3 0 0\nc.png 1 0 0 0 1 0 0\n");
    (dir, root)
}

fn dataset_kind(e: &Error) -> bool {
    matches!(e, Error::Dataset { .. } | Error::Io { .. })
}

/// Opens `root` as a dataset; every query's ground truth is read too.
fn open_dataset(root: &Path) -> Verdict {
    match Dataset::open(root, &DatasetOptions::default()) {
        Ok(ds) => {
            for q in &ds.queries {
                if let Err(e) = ds.ground_truth(q) {
                    return Verdict::Violation(format!("an opened dataset fails its ground truth: {e}"));
                }
            }
            Verdict::Accepted
        }
        // an I/O error names the path it failed on, which a manifest may put outside the root
        Err(e @ Error::Io { .. }) => Verdict::refused(&e, "", dataset_kind),
        Err(e) => Verdict::refused(&e, &root.display().to_string(), dataset_kind),
    }
}

pub fn dataset_manifest() -> Option<Target> {
    let (dir, root) = dataset_root();
    let seeds = MANIFESTS;
    let manifest = root.join(semlook::dataset::MANIFEST);
    let run = move |b: &[u8]| {
        let _keep = &dir;
        if let Err(e) = std::fs::write(&manifest, b) {
            return Verdict::Violation(format!("fixture: {e}"));
        }
        open_dataset(&root)
    };
    Some(Target {
        name: "dataset_manifest",
        seeds: seeds.iter().map(|s| s.as_bytes().to_vec()).collect(),
        fixup: None,
        quick: 400,
        run: Box::new(run),
    })
}

/// One manifest per layout, over the files of [`dataset_root`].
const MANIFESTS: [&str; 3] = [
    r#"{"format": "semlook-dataset", "version": 1, "layout": "synthia", "label_ids": "train_id", "reference": "day", "queries": ["night"], "ground_truth": {"max_distance": 7.0}}"#,
    r#"{"format": "semlook-dataset", "version": 1, "layout": "folders", "reference": {"name": "db", "images": "imgs/db", "poses": "imgs/poses.txt", "pose_format": "quat_center"}, "queries": [{"name": "q", "images": "imgs/q", "labels": "imgs/q", "poses": "imgs/poses.txt", "pose_format": "quat_translation"}], "ground_truth": {"max_distance": 2.0, "max_angle_deg": 30}}"#,
    r#"{"format": "semlook-dataset", "version": 1, "layout": "explicit", "name": "x", "label_format": "palette", "label_ids": [[0, "road"], [7, "void"]], "reference": {"name": "r", "frames": [{"id": "r0", "image": "imgs/db/a.png", "pose": {"position": [0, 0, 0], "forward": [0, 0, 1]}}, {"id": "r1", "labels": "imgs/db/b.png"}]}, "queries": [{"name": "q", "frames": [{"id": "q0", "image": "imgs/q/c.png", "ground_truth": [1, 0]}]}]}"#,
];

/// The manifests of [`dataset_manifest`] with values changed by the fuzz bytes (structure kept,
/// so the layouts' readers are reached rather than the JSON parser).
pub fn dataset_values() -> Option<Target> {
    let (dir, root) = dataset_root();
    let manifests: Vec<serde_json::Value> = MANIFESTS.iter().map(|m| serde_json::from_str(m).expect("seed manifest")).collect();
    let manifest = root.join(semlook::dataset::MANIFEST);
    let run = move |b: &[u8]| {
        let _keep = &dir;
        let mut e = crate::mutate::Entropy::new(b);
        let mut v = manifests[e.below(manifests.len())].clone();
        crate::mutate::json_mutate(&mut e, &mut v);
        if let Err(err) = std::fs::write(&manifest, v.to_string()) {
            return Verdict::Violation(format!("fixture: {err}"));
        }
        open_dataset(&root)
    };
    let mut seeds = vec![vec![0u8; 4], vec![1, 0, 0, 0], vec![2, 0, 0, 0]];
    seeds.extend(random_seeds(7, 13, 128));
    Some(Target { name: "dataset_values", seeds, fixup: None, quick: 300, run: Box::new(run) })
}

pub fn ground_truth_csv() -> Option<Target> {
    let dir = tempfile::tempdir().expect("temp dir");
    let root = dir.path().to_path_buf();
    for f in ["ref/r0.jpg", "ref/r1.jpg", "ref/r2.png", "query/q0.jpg", "query/q1.jpg"] {
        touch(&root.join(f), "");
    }
    let seeds = [
        "query,reference\nquery/q0.jpg,ref/r0.jpg\nquery/q0.jpg,ref/r1.jpg\nquery/q1.jpg,ref/r2.png\n",
        "Reference, Query, note\n ref/r1.jpg , ./query/q1.jpg, \"a, b\"\nref/../ref/r0.jpg,query/q0.jpg,x\n",
        "\u{feff}query,reference\r\nquery/q1.jpg,ref/r0.jpg\r\n",
    ];
    let csv = root.join("ground_truth.csv");
    let run = move |b: &[u8]| {
        let _keep = &dir;
        if let Err(e) = std::fs::write(&csv, b) {
            return Verdict::Violation(format!("fixture: {e}"));
        }
        open_dataset(&root)
    };
    Some(Target {
        name: "ground_truth_csv",
        seeds: seeds.iter().map(|s| s.as_bytes().to_vec()).collect(),
        fixup: None,
        quick: 400,
        run: Box::new(run),
    })
}

pub fn npy_fixtures() -> Vec<Vec<u8>> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    ["vprbench_lists.npy", "vprbench_arrays_p2.npy", "vprbench_rows.npy"].iter().map(|n| std::fs::read(dir.join(n)).expect("fixture .npy")).collect()
}

pub fn ground_truth_npy() -> Option<Target> {
    let name = "fuzz/ground_truth_new.npy";
    let run = move |b: &[u8]| match semlook::dataset::pairs::parse_npy_ground_truth(b, Path::new(name), 64, 64) {
        Ok(gt) if gt.len() == 64 && gt.iter().flatten().all(|&r| r < 64) => Verdict::Accepted,
        Ok(gt) => Verdict::Violation(format!("ground truth out of range: {gt:?}")),
        Err(e) => Verdict::refused(&e, name, |e| matches!(e, Error::Dataset { .. })),
    };
    Some(Target { name: "ground_truth_npy", seeds: npy_fixtures(), fixup: None, quick: 600, run: Box::new(run) })
}

pub fn pose_lists() -> Option<Target> {
    let seeds = [
        "# name qw qx qy qz x y z\na.jpg 1 0 0 0 2 0 0\nb.jpg 0.7071 0 0.7071 0 -2 0.5 1e3\n",
        "m.png 1 0 0 5 0 1 0 0 0 0 1 -3 0 0 0 1\n",
        "1 0 0 0 0 1 0 0 0 0 1 0 4.5 1.6 -20.25 1\n",
    ];
    let name = "fuzz/poses.txt";
    let run = move |b: &[u8]| {
        let text = String::from_utf8_lossy(b);
        let mut verdict = Verdict::Refused;
        let typed = |e: &Error| matches!(e, Error::Dataset { .. });
        let formats = [PoseFormat::QuatCenter, PoseFormat::QuatTranslation, PoseFormat::MatrixCamToWorld, PoseFormat::MatrixWorldToCam];
        for f in formats {
            match semlook::dataset::parse_pose_list(&text, Path::new(name), f) {
                Ok(_) => verdict = Verdict::Accepted,
                Err(e) => {
                    if let v @ Verdict::Violation(_) = Verdict::refused(&e, name, typed) {
                        return v;
                    }
                }
            }
        }
        match semlook::dataset::parse_synthia_pose(&text, Path::new(name)) {
            Ok(_) => Verdict::Accepted,
            Err(e) => match Verdict::refused(&e, name, typed) {
                Verdict::Refused => verdict,
                v => v,
            },
        }
    };
    Some(Target { name: "pose_lists", seeds: seeds.iter().map(|s| s.as_bytes().to_vec()).collect(), fixup: None, quick: 400, run: Box::new(run) })
}

/// Parses a config; an accepted one must write itself back unchanged and run the pipeline on a
/// small label map of its own class table, in every setting.
fn config_run(text: &str) -> Verdict {
    let name = "fuzz.toml";
    let cfg = match Config::from_toml(text, name) {
        Ok(c) => c,
        Err(e) => return Verdict::refused(&e, name, |e| matches!(e, Error::InvalidConfig { .. })),
    };
    let back = match cfg.to_toml().and_then(|t| Config::from_toml(&t, "written")) {
        Ok(b) => b,
        Err(e) => return Verdict::Violation(format!("an accepted config does not write itself back: {e}")),
    };
    if back != cfg {
        return Verdict::Violation("an accepted config reads back differently".into());
    }
    let mut cfg = cfg;
    cfg.appearance.model = semlook::config::AppearanceModelKind::None;
    cfg.models.default_segmenter = false;
    let table = match ClassTable::from_config(&cfg.classes) {
        Ok(t) => t,
        Err(e) => return Verdict::Violation(format!("a validated class table fails: {e}")),
    };
    let classes =
        (0..96 * 64).map(|i| if i % 37 == 0 { semlook::classes::VOID } else { ((i / 96 / 16 + i % 96 / 24) % table.len()) as u8 }).collect();
    let map = match semlook::input::LabelMap::new(96, 64, classes, &table) {
        Ok(m) => m,
        Err(e) => return Verdict::Violation(format!("label map: {e}")),
    };
    let enc = match semlook::encode::Encoder::new(&cfg) {
        Ok(e) => e,
        Err(e) => return Verdict::Violation(format!("a validated config makes no encoder: {e}")),
    };
    let mut set = enc.descriptor_set();
    for id in ["a", "b"] {
        match enc.encode_labels(id, &map, &mut Default::default()) {
            Ok((img, _)) => {
                if let Err(e) = set.push(&img) {
                    return Verdict::Violation(format!("push: {e}"));
                }
            }
            Err(e) => return Verdict::Violation(format!("a validated config fails to encode: {e}")),
        }
    }
    for setting in semlook::matching::Setting::SEMLOOK {
        let m = match semlook::matching::match_batch(&set, &set, setting, &cfg) {
            Ok((m, _)) => m,
            Err(e) => return Verdict::Violation(format!("{setting}: {e}")),
        };
        if m.len() != 2 || m.iter().any(|q| q.ranked.is_empty()) {
            return Verdict::Violation(format!("{setting}: {} rankings", m.len()));
        }
    }
    Verdict::Accepted
}

pub fn config_toml() -> Option<Target> {
    let mut seeds: Vec<Vec<u8>> = [Config::default(), Config::camvid(), Config::without_appearance()]
        .iter()
        .map(|c| c.to_toml().expect("defaults write").into_bytes())
        .collect();
    seeds.push(b"[matching]\ntop_k = 3\ntile = 2\n[eval]\nrecall_at = [1, 2, 3]\n[global]\nwidth = 16\nheight = 12\nssim_window = 5\n".to_vec());
    seeds.push(b"[classes]\ntable = [{name = \"a\", color = [1, 2, 3]}, {name = \"b\", color = [4, 5, 6], dynamic = true}]\nlabel_ids = [[0, \"a\"], [9, \"b\"], [255, \"void\"]]\nexclude = [\"b\"]\n[segmentation]\nclass_map = [\"a\", \"void\"]\n".to_vec());
    let run = |b: &[u8]| config_run(&String::from_utf8_lossy(b));
    Some(Target { name: "config_toml", seeds, fixup: None, quick: 150, run: Box::new(run) })
}

/// Keys of the config file and the kind of value each takes.
const KEYS: &[(&str, &str, &str)] = &[
    ("input", "working_long_side", "int"),
    ("objects", "min_area_fraction", "real"),
    ("objects", "max_objects", "int"),
    ("objects", "area", "enum:pixels,contour"),
    ("global", "truncation", "real"),
    ("global", "width", "int"),
    ("global", "height", "int"),
    ("global", "ssim_window", "int"),
    ("global", "ssim_k1", "real"),
    ("global", "ssim_k2", "real"),
    ("global", "ssim_sample_covariance", "bool"),
    ("local", "neighbours", "int"),
    ("local", "tie_tolerance", "real"),
    ("appearance", "nms_radius", "int"),
    ("appearance", "max_keypoints", "int"),
    ("appearance", "vlad_centres", "int"),
    ("appearance", "codebook_images", "int"),
    ("appearance", "codebook_iterations", "int"),
    ("appearance", "codebook_seed", "int"),
    ("appearance", "sampling", "enum:dense,keypoints"),
    ("segmentation", "input_width", "int"),
    ("segmentation", "input_height", "int"),
    ("segmentation", "mean", "reals"),
    ("segmentation", "std", "reals"),
    ("segmentation", "brighten_dark", "real"),
    ("segmentation", "class_map", "names"),
    ("classes", "exclude", "names"),
    ("classes", "void_ids", "ints"),
    ("classes", "label_ids", "enum:train_id,cityscapes_label_id,synthia,camvid,nope"),
    ("classes", "table", "enum:cityscapes,camvid,mapillary"),
    ("similarity", "w_area", "real"),
    ("similarity", "w_appearance", "real"),
    ("similarity", "w_neighbours", "real"),
    ("similarity", "position", "enum:linear,gaussian"),
    ("similarity", "position_sigma", "real"),
    ("similarity", "missing_appearance", "enum:neutral,drop"),
    ("similarity", "assignment", "enum:greedy,best_match"),
    ("similarity", "tree_weight", "enum:uniform,area,sqrt_area,descriptors"),
    ("similarity", "normalise", "enum:larger_forest,geometric_mean"),
    ("matching", "top_k", "int"),
    ("matching", "tile", "int"),
    ("matching", "score", "enum:fine,fine_times_global"),
    ("eval", "recall_at", "ints"),
];

fn int(e: &mut Entropy) -> String {
    let v: i64 = match e.below(6) {
        0 => e.below(8) as i64,
        1 => e.below(100) as i64 * 2 + 1,
        2 => [0, -1, 1, 255, 256, 1023, 1024, 4096, 65535, 65536, 1 << 31, i64::MAX][e.below(12)],
        3 => -(e.below(1000) as i64),
        4 => e.u32() as i64,
        _ => 3 + e.below(20) as i64,
    };
    v.to_string()
}

fn real(e: &mut Entropy) -> String {
    match e.below(5) {
        0 => ["nan", "inf", "-inf", "-0.0", "1e308", "1e-320", "0.0", "1.0", "-1.0"][e.below(9)].into(),
        1 => format!("{}.{}", e.below(4), e.below(1000)),
        2 => format!("{}", e.u32() as f64 / 7.0),
        _ => format!("0.{:03}", e.below(1000)),
    }
}

/// A config file built from the fuzz bytes: known keys with values of the right kind, often out
/// of range, sometimes of the wrong kind.
fn structured(e: &mut Entropy) -> String {
    let names = ["road", "sky", "car", "void", "dragon", ""];
    let mut sections: Vec<(&str, Vec<String>)> = Vec::new();
    for _ in 0..1 + e.below(6) {
        let (section, key, kind) = *e.pick(KEYS);
        let kind = if e.chance(12) { *e.pick(&["int", "real", "bool", "names"]) } else { kind };
        let value = match kind {
            "int" => int(e),
            "real" => real(e),
            "bool" => ["true", "false"][e.below(2)].into(),
            "ints" => format!("[{}]", (0..e.below(20)).map(|_| int(e)).collect::<Vec<_>>().join(", ")),
            "reals" => format!("[{}]", (0..e.below(5)).map(|_| real(e)).collect::<Vec<_>>().join(", ")),
            "names" => format!("[{}]", (0..e.below(25)).map(|_| format!("{:?}", e.pick(&names))).collect::<Vec<_>>().join(", ")),
            enumerated => {
                let options: Vec<&str> = enumerated.trim_start_matches("enum:").split(',').collect();
                format!("{:?}", e.pick(&options))
            }
        };
        match sections.iter_mut().find(|s| s.0 == section) {
            Some(s) => s.1.push(format!("{key} = {value}")),
            None => sections.push((section, vec![format!("{key} = {value}")])),
        }
    }
    sections.iter().map(|(s, lines)| format!("[{s}]\n{}\n", lines.join("\n"))).collect()
}

pub fn config_structured() -> Option<Target> {
    let run = |b: &[u8]| config_run(&structured(&mut Entropy::new(b)));
    Some(Target { name: "config_structured", seeds: random_seeds(3, 16, 64), fixup: None, quick: 150, run: Box::new(run) })
}

pub fn pickle() -> Option<Target> {
    // the pickles inside the .npy fixtures (after their headers) and a state dict's
    let mut seeds: Vec<Vec<u8>> = npy_fixtures()
        .into_iter()
        .filter_map(|b| {
            let len = u16::from_le_bytes([*b.get(8)?, *b.get(9)?]) as usize;
            b.get(10 + len..).map(<[u8]>::to_vec)
        })
        .collect();
    seeds.push(crate::models::tiny_xfeat().pickle());
    let run = |b: &[u8]| match semlook::nn::pickle::Pickle::load(b) {
        Ok(p) => {
            // every reachable id reads back
            let _ = (p.seq(p.root), p.pairs(p.root), p.int(p.root), p.str(p.root));
            Verdict::Accepted
        }
        Err(_) => Verdict::Refused,
    };
    Some(Target { name: "pickle", seeds, fixup: None, quick: 1500, run: Box::new(run) })
}
