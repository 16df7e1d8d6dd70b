//! Label maps from RGB with ONNX segmenters: a tiny model built by scripts/make_tiny_segmenter.py
//! (checked in), and the real ESPNet Cityscapes model on real street frames when ../shared holds them.

mod common;

use image::{Rgb, RgbImage};
use semlook::classes::ClassTable;
use semlook::config::{Config, SegmentationConfig};
use semlook::networks::segmenter::Segmenter;
use std::path::{Path, PathBuf};

fn tiny() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/tiny_segmenter.onnx")
}

fn tiny_cfg() -> SegmentationConfig {
    SegmentationConfig { input_width: 64, input_height: 48, class_map: vec!["road".into(), "vegetation".into(), "sky".into()], ..Default::default() }
}

/// ONNX Runtime must be there under CI; elsewhere the tests skip saying why.
fn load(path: &Path, cfg: &SegmentationConfig) -> Option<Segmenter> {
    match Segmenter::load(path, cfg, &ClassTable::cityscapes(), None) {
        Ok(s) => Some(s),
        Err(e @ semlook::Error::Model { .. }) if e.to_string().contains("ONNX Runtime library") => {
            common::skip_unless_required("REQUIRE_MODELS", e);
            None
        }
        Err(e) => panic!("{e}"),
    }
}

fn stripes(w: u32, h: u32, flip: bool) -> RgbImage {
    RgbImage::from_fn(w, h, |x, _| {
        let band = (x * 3 / w) as usize;
        let band = if flip { 2 - band } else { band };
        [Rgb([220, 30, 30]), Rgb([30, 220, 30]), Rgb([30, 30, 220])][band]
    })
}

#[test]
fn tiny_segmenter_maps_channels_to_classes_and_batches() {
    let Some(seg) = load(&tiny(), &tiny_cfg()) else { return };
    let (a, b) = (stripes(90, 40, false), stripes(90, 40, true));
    let la = seg.segment(&a, Path::new("a.png")).unwrap();
    assert_eq!((la.width(), la.height()), (90, 40), "label map has the image's size");
    for (x, class) in [(10, 0u8), (45, 8), (80, 10)] {
        assert_eq!(la.get(x, 20), class, "pixel x={x}");
    }
    let both = seg.segment_batch(&[&a, &b]).unwrap();
    assert_eq!(both[0], la);
    assert_eq!(both[1].get(10, 20), 10);
    assert_eq!(both[1], seg.segment(&b, Path::new("b.png")).unwrap());
}

#[test]
fn segmenter_adapters_are_checked() {
    let mut cfg = tiny_cfg();
    cfg.class_map = vec!["road".into(), "vegetation".into(), "dragon".into()];
    match Segmenter::load(&tiny(), &cfg, &ClassTable::cityscapes(), None) {
        Err(semlook::Error::InvalidConfig { reason, .. }) => assert!(reason.contains("dragon")),
        other => panic!("unknown class accepted: {other:?}"),
    }
    if load(&tiny(), &tiny_cfg()).is_none() {
        return;
    }
    // the model declares 3 output channels: a 2-class map is refused when loading
    let two = SegmentationConfig { class_map: vec!["road".into(), "sky".into()], ..tiny_cfg() };
    let err = Segmenter::load(&tiny(), &two, &ClassTable::cityscapes(), None).unwrap_err();
    assert!(err.to_string().contains("3 output channels") && err.to_string().contains("tiny_segmenter.onnx"), "{err}");
    let missing = Segmenter::load(Path::new("/nowhere/model.onnx"), &tiny_cfg(), &ClassTable::cityscapes(), None);
    assert!(matches!(missing, Err(semlook::Error::Model { .. })));
}

/// Frames without label maps are segmented by the configured network, end to end.
#[test]
fn encoding_from_rgb_alone() {
    if load(&tiny(), &tiny_cfg()).is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let img = dir.path().join("frame.png");
    stripes(96, 64, false).save(&img).unwrap();
    let mut cfg = Config::without_appearance();
    cfg.segmentation = tiny_cfg();
    cfg.models.segmenter_onnx = Some(tiny());
    let enc = semlook::encode::Encoder::new(&cfg).unwrap();
    let src = semlook::input::FrameSource { id: "f".into(), image: Some(img.clone()), labels: None };
    let (e, _) = enc.encode_source(&src, Default::default(), &mut Default::default()).unwrap();
    let mut classes = e.forest.classes.clone();
    classes.sort();
    assert_eq!(classes, vec![0, 8, 10]);
    // without a segmenter the same frame is refused, naming the image
    let mut none = Config::without_appearance();
    none.models.default_segmenter = false;
    let plain = semlook::encode::Encoder::new(&none).unwrap();
    let err = plain.encode_source(&src, Default::default(), &mut Default::default()).unwrap_err();
    assert!(matches!(err, semlook::Error::NoLabels { .. }) && err.to_string().contains("frame.png"), "{err}");
}

/// A segmenter that fails to load on first use (a file that is not a network, here with the
/// tiny model's 3 classes against a 2-class map) is named once in the error the frame gets, with
/// the reason: the lazy loader keeps the model error as it is instead of wrapping it again.
#[test]
fn a_segmenter_that_fails_to_load_is_named_once() {
    if load(&tiny(), &tiny_cfg()).is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let img = dir.path().join("frame.png");
    stripes(96, 64, false).save(&img).unwrap();
    let mut cfg = Config::without_appearance();
    cfg.segmentation = SegmentationConfig { class_map: vec!["road".into(), "sky".into()], ..tiny_cfg() };
    cfg.models.segmenter_onnx = Some(tiny());
    let enc = semlook::encode::Encoder::new(&cfg).unwrap();
    let src = semlook::input::FrameSource { id: "f".into(), image: Some(img), labels: None };
    for _ in 0..2 {
        let err = enc.encode_source(&src, Default::default(), &mut Default::default()).unwrap_err();
        let text = err.to_string();
        assert!(matches!(err, semlook::Error::Model { .. }) && text.contains("3 output channels"), "{text}");
        assert_eq!(text.matches("tiny_segmenter.onnx").count(), 1, "the model named more than once: {text}");
    }
}

/// ESPNet on the two real Cityscapes frames: a plausible street segmentation, and objects and
/// trees that behave on it.
#[test]
fn espnet_segments_real_street_frames_plausibly() {
    let (Some(model), Some(frames)) = (common::shared_or_required("models/espnet_cityscapes.onnx"), common::shared_or_required("data/street-frames"))
    else {
        return;
    };
    let cfg = Config::default();
    let Some(seg) = load(&model, &cfg.segmentation) else { return };
    let table = ClassTable::cityscapes();
    for name in ["frankfurt_000000_000294_leftImg8bit.png", "frankfurt_000000_000576_leftImg8bit.png"] {
        let rgb = image::open(frames.join(name)).unwrap().to_rgb8();
        let labels = seg.segment(&rgb, Path::new(name)).unwrap();
        if let Some(dir) = std::env::var_os("SEMLOOK_DUMP") {
            let img = RgbImage::from_fn(2048, 1024, |x, y| Rgb(table.color(labels.get(x, y))));
            image::imageops::resize(&img, 1024, 512, image::imageops::FilterType::Nearest).save(Path::new(&dir).join(name)).unwrap();
        }
        assert_eq!((labels.width(), labels.height()), (2048, 1024));
        let n = labels.classes().len() as f64;
        let share = |c: &str| labels.classes().iter().filter(|&&v| v == table.index(c).unwrap()).count() as f64 / n;
        eprintln!(
            "{name}: road {:.2} sidewalk {:.2} building {:.2} vegetation {:.2} sky {:.2} car {:.2}",
            share("road"),
            share("sidewalk"),
            share("building"),
            share("vegetation"),
            share("sky"),
            share("car")
        );
        assert!(share("road") > 0.15, "a street frame is mostly road at the bottom");
        assert!(share("building") + share("vegetation") > 0.2);
        assert!(share("car") > 0.005, "Frankfurt streets have parked cars");
        // below the horizon in the middle is road; the top rows are not; the ego car's hood at
        // the bottom is void (no Cityscapes train class)
        assert_eq!(labels.get(1024, 850), table.index("road").unwrap());
        assert_ne!(labels.get(1024, 5), table.index("road").unwrap());
        assert_eq!(labels.get(1024, 1020), semlook::classes::VOID);
        let objects = semlook::objects::extract_objects(&labels, &table, &cfg.objects);
        assert!(objects.objects.len() >= 8 && objects.objects.len() <= cfg.objects.max_objects, "{} objects", objects.objects.len());
        let forest = semlook::local::build_forest(&objects, &cfg.local);
        assert!((0..forest.len()).all(|k| forest.neighbours_of(k).len() == 3 && !forest.neighbours_of(k).contains(&k)));
    }
}
