//! Bad inputs get typed errors that name the file, and never damage a stored map; nor does a
//! write that fails inside `Map::add`.

mod common;

use image::{GrayImage, Luma, Rgb, RgbImage};
use semlook::classes::ClassTable;
use semlook::config::Config;
use semlook::descriptors::DescriptorSet;
use semlook::encode::Encoder;
use semlook::error::Error;
use semlook::input::{load_frame_labels, load_label_map, FrameSource, LabelFormat};
use semlook::map::{files, Map};
use std::path::Path;

fn grey(path: &Path, w: u32, h: u32, id: u8) {
    GrayImage::from_pixel(w, h, Luma([id])).save(path).unwrap();
}

#[test]
fn each_bad_label_map_is_refused_with_its_file_named() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let t = ClassTable::cityscapes();
    let f = LabelFormat::Auto;

    let p = d.join("unknown_id.png");
    let mut g = GrayImage::from_pixel(8, 8, Luma([0]));
    g.put_pixel(3, 5, Luma([77]));
    g.save(&p).unwrap();
    let e = load_label_map(&p, &t, f).unwrap_err();
    assert!(matches!(e, Error::UnknownClassId { id: 77, x: 3, y: 5, .. }), "{e}");
    assert!(e.to_string().contains("unknown_id.png"));

    let p = d.join("unknown_colour.png");
    RgbImage::from_pixel(4, 4, Rgb([12, 34, 56])).save(&p).unwrap();
    let e = load_label_map(&p, &t, f).unwrap_err();
    assert!(matches!(e, Error::UnknownClassColor { rgb: [12, 34, 56], .. }) && e.to_string().contains("unknown_colour.png"), "{e}");

    let p = d.join("empty.png");
    std::fs::write(&p, b"").unwrap();
    let e = load_label_map(&p, &t, f).unwrap_err();
    assert!(matches!(e, Error::EmptyImage { .. }) && e.to_string().contains("empty.png"), "{e}");

    let p = d.join("text.png");
    std::fs::write(&p, b"this is not a png").unwrap();
    let e = load_label_map(&p, &t, f).unwrap_err();
    assert!(matches!(e, Error::ImageDecode { .. }) && e.to_string().contains("text.png"), "{e}");

    let p = d.join("truncated.png");
    let mut bytes = Vec::new();
    GrayImage::from_pixel(64, 64, Luma([0])).write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    assert!(load_label_map(&p, &t, f).is_err(), "truncated png accepted");

    let e = load_label_map(&d.join("missing.png"), &t, f).unwrap_err();
    assert!(matches!(e, Error::Io { .. }) && e.to_string().contains("missing.png"), "{e}");

    // size mismatch between image and label map
    let img = d.join("img.png");
    RgbImage::new(20, 10).save(&img).unwrap();
    let lab = d.join("lab.png");
    grey(&lab, 10, 10, 0);
    let src = FrameSource { id: "x".into(), image: Some(img.clone()), labels: Some(lab.clone()) };
    let e = load_frame_labels(&src, &t, f).unwrap_err();
    assert!(matches!(e, Error::SizeMismatch { image_size: (20, 10), label_size: (10, 10), .. }), "{e}");
    assert!(e.to_string().contains("lab.png") && e.to_string().contains("img.png"));

    // an image without labels and no segmenter
    let src = FrameSource { id: "y".into(), image: Some(img), labels: None };
    assert!(matches!(load_frame_labels(&src, &t, f), Err(Error::NoLabels { .. })));
}

#[test]
fn sixteen_bit_and_first_channel_ids_decode() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("l16.png");
    let mut g = image::ImageBuffer::<Luma<u16>, Vec<u16>>::from_pixel(4, 2, Luma([8u16]));
    g.put_pixel(0, 0, Luma([255]));
    g.save(&p).unwrap();
    let m = load_label_map(&p, &ClassTable::cityscapes(), LabelFormat::Auto).unwrap();
    assert_eq!(m.classes()[0], semlook::classes::VOID);
    assert_eq!(m.classes()[1], 8);
    // ids past one byte keep all sixteen bits: 264 and 8 share their low byte, 1000 has a high
    // one; a decoder that drops or scales the high byte reads 264 as 8, or fails on 1000
    let cfg = semlook::config::ClassesConfig {
        label_ids: semlook::config::LabelIds::Custom(vec![(8, "road".into()), (264, "car".into()), (1000, "sky".into())]),
        ..Default::default()
    };
    let custom = ClassTable::from_config(&cfg).unwrap();
    let mut g = image::ImageBuffer::<Luma<u16>, Vec<u16>>::from_pixel(3, 1, Luma([8u16]));
    g.put_pixel(1, 0, Luma([264]));
    g.put_pixel(2, 0, Luma([1000]));
    g.save(&p).unwrap();
    let m = load_label_map(&p, &custom, LabelFormat::Auto).unwrap();
    let names: Vec<&str> = m.classes().iter().map(|&c| custom.name(c)).collect();
    assert_eq!(names, ["road", "car", "sky"]);
    // SYNTHIA style: class in the red channel of a colour file
    let p = dir.path().join("synthia.png");
    RgbImage::from_pixel(3, 3, Rgb([3, 77, 12])).save(&p).unwrap();
    let cfg = semlook::config::ClassesConfig { label_ids: semlook::config::LabelIds::Named("synthia".into()), ..Default::default() };
    let t = ClassTable::from_config(&cfg).unwrap();
    assert!(load_label_map(&p, &t, LabelFormat::FirstChannel).unwrap().classes().iter().all(|&c| c == 0));
}

#[test]
fn a_batch_with_a_bad_file_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let path = dir.path().join("map");
    let set = common::encode(&cfg, &common::label_maps(4, 64, 48), "ref");
    Map::create(&path, &cfg.encoding(), &set, None).unwrap();
    let before = common::snapshot(&path);
    // a batch with one good and one bad file: encoding fails before anything is written
    let good = dir.path().join("good.png");
    grey(&good, 64, 48, 0);
    let bad = dir.path().join("bad.png");
    grey(&bad, 64, 48, 99);
    let sources =
        vec![FrameSource { id: "good".into(), image: None, labels: Some(good) }, FrameSource { id: "bad".into(), image: None, labels: Some(bad) }];
    let enc = Encoder::new(&cfg).unwrap();
    let results = enc.encode_all(&sources, LabelFormat::Auto, &|| {});
    let err = semlook::encode::collect_encoded(results, false).unwrap_err();
    assert!(err.to_string().contains("bad.png"), "{err}");
    assert_eq!(common::snapshot(&path), before);
    assert_eq!(Map::open(&path).unwrap().len(), 4);
    // with skipping, the good one is stored and the bad one reported
    let results = enc.encode_all(&sources, LabelFormat::Auto, &|| {});
    let (imgs, _, skipped) = semlook::encode::collect_encoded(results, true).unwrap();
    assert_eq!((imgs.len(), skipped.len()), (1, 1));
}

fn bits(set: &DescriptorSet) -> Vec<u32> {
    set.globals.iter().chain(&set.tree_areas).chain(&set.tree_centroids).map(|v| v.to_bits()).collect()
}

/// A write that fails inside `Map::add` (the segment file; or the manifest, once the segment is in
/// place) gives a typed error naming the file, and the map reads back as it was: every stored image
/// bit for bit, none of the new ones. The next add then stores them.
#[test]
fn a_failed_add_loses_nothing_already_stored() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let path = dir.path().join("map");
    let maps = common::label_maps(6, 64, 48);
    let stored = common::encode(&cfg, &maps[..4], "ref");
    let new = common::encode(&cfg, &maps[4..], "new");
    Map::create(&path, &cfg.encoding(), &stored, None).unwrap();
    for (fault, named) in [("segment-", ".segment-"), ("manifest.json", ".manifest.json.tmp")] {
        let manifest = std::fs::read(path.join("manifest.json")).unwrap();
        let mut map = Map::open(&path).unwrap();
        files::fail_next_write(Some(fault));
        let result = map.add(&new);
        files::fail_next_write(None);
        match result {
            Err(e @ Error::Io { .. }) if e.to_string().contains(named) => {}
            other => panic!("{fault}: expected an I/O error naming {named}, got {other:?}"),
        }
        let back = Map::open(&path).unwrap_or_else(|e| panic!("{fault}: the map no longer opens after a failed add: {e}"));
        let back = back.to_descriptor_set().unwrap_or_else(|e| panic!("{fault}: the map no longer reads back after a failed add: {e}"));
        assert_eq!(back.ids, stored.ids, "{fault}: images lost or the failed ones stored");
        assert_eq!((bits(&back), &back), (bits(&stored), &stored), "{fault}: stored images changed");
        assert_eq!(std::fs::read(path.join("manifest.json")).unwrap(), manifest, "{fault}: the manifest changed");
    }
    let mut map = Map::open(&path).unwrap();
    map.add(&new).unwrap();
    let mut all = stored.clone();
    all.append(&new).unwrap();
    let back = Map::open(&path).unwrap().to_descriptor_set().unwrap();
    assert_eq!((bits(&back), &back), (bits(&all), &all));
}

#[test]
fn invalid_configs_are_refused() {
    for text in [
        "[global]\nwidth = 3\n",
        "[similarity]\nw_area = -1\n",
        "[local]\ntie_tolerance = inf\n",
        "[classes]\ntable = \"mapillary\"\n",
        "[verification]\nignore_classes = [\"pedestrian\"]\n",
        "[appearance]\nignore_classes = [\"sky\", \"clouds\"]\n",
        "[verification]\nmatcher = \"superglue\"\n",
        "[verification]\nglue_threshold = 1.5\n",
        "[verification]\nglue_width_confidence = 2\n",
        "[verification]\nmatcher = \"lighterglue\"\n[appearance]\nmodel = \"onnx\"\n",
        "[verification]\nw_glue = 0.5\n[appearance]\nmodel = \"none\"\n",
    ] {
        let e = Config::from_toml(text, "bad.toml").unwrap_err();
        assert!(matches!(e, Error::InvalidConfig { .. }) && e.to_string().contains("bad.toml"), "{text}: {e}");
    }
}

/// A "zlib bomb": a grey label PNG of a few hundred kilobytes declaring 20000 x 20000 pixels (400 MB
/// decoded, under the image crate's own 512 MiB limit, 2 GB with the copies the translation
/// makes). It is refused from its header, naming the file and the sizes; before, it was decoded
/// and widened to 2.4 GB of memory.
#[test]
fn a_label_png_whose_decoded_copies_exceed_the_limit_is_refused_before_decoding() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bomb.png");
    let side = 20_000u32;
    {
        let file = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
        let mut enc = png::Encoder::new(file, side, side);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(png::Compression::Fast);
        let mut writer = enc.write_header().unwrap();
        let mut stream = writer.stream_writer().unwrap();
        let row = vec![0u8; side as usize];
        for _ in 0..side {
            stream.write_all(&row).unwrap();
        }
        stream.finish().unwrap();
    }
    let size = std::fs::metadata(&path).unwrap().len();
    assert!(size < 4 << 20, "the bomb is small on disk: {size} bytes");
    let table = semlook::classes::ClassTable::from_config(&Config::default().classes).unwrap();
    match semlook::input::load_label_map(&path, &table, semlook::input::LabelFormat::Auto) {
        Err(e @ Error::ImageDecode { .. }) => {
            let msg = e.to_string();
            assert!(msg.contains("bomb.png") && msg.contains("20000x20000") && msg.contains("MiB"), "{msg}");
        }
        other => panic!("a zlib bomb was decoded: {:?}", other.map(|m| (m.width(), m.height()))),
    }
}
