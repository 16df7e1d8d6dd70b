//! Stage 0 of the data flow: reading images and semantic label maps from files, with every
//! failure reported as a typed error naming the file.

use crate::classes::{ClassTable, VOID};
use crate::error::{Error, Result};
use image::{DynamicImage, RgbImage};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Per-pixel class indices of one image (row-major, [`VOID`] for unlabeled pixels).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LabelMap {
    width: u32,
    height: u32,
    classes: Vec<u8>,
}

impl LabelMap {
    /// Wraps class indices; fails if the size is empty or does not match, or if an index is
    /// neither a class of `table` nor VOID.
    pub fn new(width: u32, height: u32, classes: Vec<u8>, table: &ClassTable) -> Result<LabelMap> {
        if width == 0 || height == 0 {
            return Err(Error::invalid("label map", format!("empty size {width}x{height}")));
        }
        if classes.len() != width as usize * height as usize {
            return Err(Error::invalid("label map", format!("{} class values for a {width}x{height} map", classes.len())));
        }
        if let Some(i) = classes.iter().position(|&c| c != VOID && c as usize >= table.len()) {
            return Err(Error::invalid("label map", format!("pixel {i} has class index {}, the table has {} classes", classes[i], table.len())));
        }
        Ok(LabelMap { width, height, classes })
    }
    /// Wraps class indices the caller produced from a class table itself (a segmenter).
    pub(crate) fn from_classes_unchecked(width: u32, height: u32, classes: Vec<u8>) -> LabelMap {
        debug_assert_eq!(classes.len(), width as usize * height as usize);
        LabelMap { width, height, classes }
    }
    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }
    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }
    /// The class index of every pixel, row-major (width x height values).
    pub fn classes(&self) -> &[u8] {
        &self.classes
    }
    /// The class index under position (x, y) in pixels: the nearest pixel, positions outside the
    /// map clamped to its border; VOID for an empty map.
    pub fn class_near(&self, x: f32, y: f32) -> u8 {
        if self.classes.is_empty() {
            return crate::classes::VOID;
        }
        let (w, h) = (self.width as i64, self.height as i64);
        let (x, y) = ((x.round() as i64).clamp(0, w - 1), (y.round() as i64).clamp(0, h - 1));
        self.classes.get((y * w + x) as usize).copied().unwrap_or(crate::classes::VOID)
    }
    /// The class index of pixel (x, y); panics outside the map.
    pub fn get(&self, x: u32, y: u32) -> u8 {
        self.classes[(y * self.width + x) as usize]
    }
    /// Nearest-neighbour resize (class ids are never blended): pixel (x, y) of the result takes
    /// the source pixel under its centre.
    pub fn resized_nearest(&self, width: u32, height: u32) -> LabelMap {
        if (width, height) == (self.width, self.height) {
            return self.clone();
        }
        let (sw, sh) = (self.width as u64, self.height as u64);
        let cols: Vec<usize> = (0..width as u64).map(|x| ((2 * x + 1) * sw / (2 * width as u64)).min(sw - 1) as usize).collect();
        let mut classes = Vec::with_capacity(width as usize * height as usize);
        for y in 0..height as u64 {
            let sy = ((2 * y + 1) * sh / (2 * height as u64)).min(sh - 1) as usize;
            let row = &self.classes[sy * self.width as usize..(sy + 1) * self.width as usize];
            classes.extend(cols.iter().map(|&x| row[x]));
        }
        LabelMap { width, height, classes }
    }
}

impl LabelMap {
    /// A map with no class anywhere: what a frame without labels is encoded with when no
    /// segmenter is installed (only the label-free settings use such descriptors).
    pub fn void(width: u32, height: u32) -> LabelMap {
        LabelMap { width, height, classes: vec![VOID; width as usize * height as usize] }
    }
}

/// The size an image of `width` x `height` is worked at for a long side of `long_side` (0: its
/// own size): scaled down keeping the aspect ratio, never enlarged, at least 1 x 1.
pub fn working_size(width: u32, height: u32, long_side: usize) -> (u32, u32) {
    let long = width.max(height) as u64;
    if long_side == 0 || long <= long_side as u64 {
        return (width, height);
    }
    let scale = |v: u32| ((v as u64 * long_side as u64 + long / 2) / long).max(1) as u32;
    (scale(width), scale(height))
}

/// How a label-map file encodes classes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum LabelFormat {
    /// Grey (8 or 16 bit) files hold ids; colour files use the class palette.
    #[default]
    Auto,
    /// The first channel holds the id, whatever the colour type (SYNTHIA's GT/LABELS).
    FirstChannel,
    /// Colour files in the class palette (Cityscapes `*_color.png`).
    Palette,
}

/// Most bytes one decoded image may take (the image crate's default, stated here because the
/// JPEG path enforces it too): a damaged header cannot make a decoder allocate more.
pub const MAX_DECODED_BYTES: u64 = 512 << 20;

/// Bytes per pixel that a label map's translation adds to the decoded image: the class per pixel,
/// and an RGB copy for palette maps.
const LABEL_COPY_BYTES_PER_PIXEL: u64 = 4;
/// Bytes per pixel of the RGB copy an RGB image is converted to.
const RGB_COPY_BYTES_PER_PIXEL: u64 = 3;

fn read_image(path: &Path, copy_bytes_per_pixel: u64) -> Result<DynamicImage> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_bytes(bytes, path, copy_bytes_per_pixel)
}

/// An RGB image brought to `width` x `height` (area-weighted when shrinking; the same image when
/// the size is already right).
pub fn resize_rgb(img: &RgbImage, width: u32, height: u32) -> RgbImage {
    if (img.width(), img.height()) == (width, height) {
        return img.clone();
    }
    image::imageops::resize(img, width, height, image::imageops::FilterType::Triangle)
}

/// Reads an RGB image at no less than `min(full size)` (width, height) where the format lets
/// the decoder skip detail: a JPEG is decoded by its DCT at the smallest of 1/8, 1/4, 1/2 or
/// full scale that is at least that size on both sides (jpeg-decoder's scaled IDCT), which costs
/// a fraction of a full decode for a large frame. Other formats decode in full. Returns the
/// image and the size of the full image.
pub fn load_rgb_at_least(path: &Path, min: impl Fn((u32, u32)) -> (u32, u32)) -> Result<(RgbImage, (u32, u32))> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_rgb_at_least(bytes, path, min)
}

/// [`load_rgb_at_least`] on a file's bytes; `path` only names the source in errors.
pub fn decode_rgb_at_least(bytes: Vec<u8>, path: &Path, min: impl Fn((u32, u32)) -> (u32, u32)) -> Result<(RgbImage, (u32, u32))> {
    if bytes.starts_with(&[0xFF, 0xD8]) {
        if let Some(r) = decode_jpeg_scaled(&bytes, path, &min)? {
            return Ok(r);
        }
    }
    let img = decode_bytes(bytes, path, RGB_COPY_BYTES_PER_PIXEL)?.to_rgb8();
    let size = img.dimensions();
    Ok((img, size))
}

/// A JPEG decoded at a reduced scale, or `None` for the pixel formats left to the image crate.
fn decode_jpeg_scaled(bytes: &[u8], path: &Path, min: &dyn Fn((u32, u32)) -> (u32, u32)) -> Result<Option<(RgbImage, (u32, u32))>> {
    let bad = |e: jpeg_decoder::Error| Error::ImageDecode { path: path.into(), reason: e.to_string() };
    let mut d = jpeg_decoder::Decoder::new(std::io::Cursor::new(bytes));
    d.set_max_decoding_buffer_size(usize::try_from(MAX_DECODED_BYTES).unwrap_or(usize::MAX));
    d.read_info().map_err(bad)?;
    let info = d.info().ok_or_else(|| Error::ImageDecode { path: path.into(), reason: "no JPEG header".into() })?;
    let full = (info.width as u32, info.height as u32);
    if full.0 == 0 || full.1 == 0 {
        return Err(Error::EmptyImage { path: path.into(), width: full.0, height: full.1 });
    }
    let need = jpeg_decode_bytes(bytes.len(), full, info.pixel_format);
    if need > MAX_DECODED_BYTES {
        return Err(too_large(path, full, need));
    }
    let min = min(full);
    let req = (min.0.clamp(1, full.0) as u16, min.1.clamp(1, full.1) as u16);
    let (w, h) = d.scale(req.0, req.1).map_err(bad)?;
    let pixels = d.decode().map_err(bad)?;
    let format = d.info().map(|i| i.pixel_format);
    let (w, h) = (w as u32, h as u32);
    let img = match format {
        Some(jpeg_decoder::PixelFormat::RGB24) => RgbImage::from_raw(w, h, pixels),
        Some(jpeg_decoder::PixelFormat::L8) => RgbImage::from_raw(w, h, pixels.iter().flat_map(|&v| [v, v, v]).collect()),
        _ => return Ok(None),
    };
    let img = img.ok_or_else(|| Error::ImageDecode { path: path.into(), reason: "decoded JPEG has the wrong number of pixels".into() })?;
    Ok(Some((img, full)))
}

/// Largest MCU a JPEG may have, in pixels per side (8 x the largest sampling factor, 4).
const JPEG_MAX_MCU_SIDE: u64 = 32;
/// Bytes per component sample jpeg-decoder holds while decoding: the 8-bit plane its workers
/// fill as soon as the first scan starts, and the i16 coefficients of a progressive frame.
const JPEG_WORK_BYTES_PER_SAMPLE: u64 = 3;

/// What decoding a JPEG of `full` pixels costs at most, counted from its header: the file, the
/// component planes and coefficients over the MCU-padded frame, and the RGB copy. jpeg-decoder
/// checks its own limit only after the scans, while its worker threads have already sized the
/// planes from the header (a 4 GB allocation for a damaged 4 KB file), so this is checked first.
fn jpeg_decode_bytes(file_bytes: usize, full: (u32, u32), format: jpeg_decoder::PixelFormat) -> u64 {
    let components = format.pixel_bytes() as u64;
    let pad = |v: u32| u64::from(v).div_ceil(JPEG_MAX_MCU_SIDE) * JPEG_MAX_MCU_SIDE;
    let padded = pad(full.0) * pad(full.1);
    let pixels = u64::from(full.0) * u64::from(full.1);
    (file_bytes as u64).saturating_add(padded * components * JPEG_WORK_BYTES_PER_SAMPLE).saturating_add(pixels * RGB_COPY_BYTES_PER_PIXEL)
}

fn too_large(path: &Path, (w, h): (u32, u32), need: u64) -> Error {
    Error::ImageDecode {
        path: path.into(),
        reason: format!("{w}x{h} pixels would take {} MiB to decode and convert, above the limit of {} MiB", need >> 20, MAX_DECODED_BYTES >> 20),
    }
}

/// Decodes an image whose file bytes, decoded pixels and the `copy_bytes_per_pixel` its caller
/// converts them into fit [`MAX_DECODED_BYTES`] together, checked from the header before any
/// pixel is decoded (a small compressed file can declare gigabytes of pixels).
fn decode_bytes(bytes: Vec<u8>, path: &Path, copy_bytes_per_pixel: u64) -> Result<DynamicImage> {
    use image::ImageDecoder;
    if bytes.is_empty() {
        return Err(Error::EmptyImage { path: path.into(), width: 0, height: 0 });
    }
    let bad = |e: image::ImageError| Error::ImageDecode { path: path.into(), reason: e.to_string() };
    let file_bytes = bytes.len() as u64;
    let reader = image::ImageReader::new(std::io::Cursor::new(bytes)).with_guessed_format().map_err(|e| Error::io(path, e))?;
    let mut decoder = reader.into_decoder().map_err(bad)?;
    let (w, h) = decoder.dimensions();
    let pixels = u64::from(w) * u64::from(h);
    let need = file_bytes.saturating_add(pixels.saturating_mul(decoder.color_type().bytes_per_pixel() as u64 + copy_bytes_per_pixel));
    if need > MAX_DECODED_BYTES {
        return Err(too_large(path, (w, h), need));
    }
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_DECODED_BYTES);
    decoder.set_limits(limits).map_err(bad)?;
    let img = DynamicImage::from_decoder(decoder).map_err(bad)?;
    if img.width() == 0 || img.height() == 0 {
        return Err(Error::EmptyImage { path: path.into(), width: img.width(), height: img.height() });
    }
    Ok(img)
}

/// Reads an RGB image (png or jpeg); alpha is dropped, grey is expanded.
pub fn load_rgb(path: &Path) -> Result<RgbImage> {
    Ok(read_image(path, RGB_COPY_BYTES_PER_PIXEL)?.to_rgb8())
}

/// Reads a label map and translates its ids or colours through `table`.
pub fn load_label_map(path: &Path, table: &ClassTable, format: LabelFormat) -> Result<LabelMap> {
    let img = read_image(path, LABEL_COPY_BYTES_PER_PIXEL)?;
    decode_label_image(&img, path, table, format)
}

/// [`load_label_map`] on a file's bytes; `path` only names the source in errors.
pub fn decode_label_bytes(bytes: Vec<u8>, path: &Path, table: &ClassTable, format: LabelFormat) -> Result<LabelMap> {
    decode_label_image(&decode_bytes(bytes, path, LABEL_COPY_BYTES_PER_PIXEL)?, path, table, format)
}

/// Translates a decoded label image; `path` only names the source in errors.
pub fn decode_label_image(img: &DynamicImage, path: &Path, table: &ClassTable, format: LabelFormat) -> Result<LabelMap> {
    let (w, h) = (img.width(), img.height());
    let grey =
        matches!(img, DynamicImage::ImageLuma8(_) | DynamicImage::ImageLuma16(_) | DynamicImage::ImageLumaA8(_) | DynamicImage::ImageLumaA16(_));
    let mut classes = Vec::new();
    let by_ids = format == LabelFormat::FirstChannel || (format == LabelFormat::Auto && grey);
    if by_ids {
        let ids: Box<dyn Iterator<Item = u32>> = match img {
            DynamicImage::ImageLuma8(g) => Box::new(g.pixels().map(|p| p.0[0] as u32)),
            DynamicImage::ImageLumaA8(g) => Box::new(g.pixels().map(|p| p.0[0] as u32)),
            DynamicImage::ImageRgb8(g) => Box::new(g.pixels().map(|p| p.0[0] as u32)),
            DynamicImage::ImageRgba8(g) => Box::new(g.pixels().map(|p| p.0[0] as u32)),
            DynamicImage::ImageLuma16(g) => Box::new(g.pixels().map(|p| p.0[0] as u32)),
            DynamicImage::ImageLumaA16(g) => Box::new(g.pixels().map(|p| p.0[0] as u32)),
            DynamicImage::ImageRgb16(g) => Box::new(g.pixels().map(|p| p.0[0] as u32)),
            DynamicImage::ImageRgba16(g) => Box::new(g.pixels().map(|p| p.0[0] as u32)),
            _ => return Err(Error::UnsupportedLabelFormat { path: path.into(), reason: format!("{:?} pixels cannot hold class ids", img.color()) }),
        };
        classes = classes_of_ids(ids, w, path, table)?;
    } else {
        if grey {
            return Err(Error::UnsupportedLabelFormat { path: path.into(), reason: "palette format asked for, but the file is grey".into() });
        }
        let rgb = img.to_rgb8();
        classes.reserve_exact(w as usize * h as usize);
        let mut last = ([0u8; 3], None::<u8>);
        for (i, p) in rgb.pixels().enumerate() {
            let c = match last {
                (colour, Some(c)) if colour == p.0 => c,
                _ => {
                    let c = table.class_of_color(p.0).ok_or(Error::UnknownClassColor {
                        path: path.into(),
                        rgb: p.0,
                        x: i as u32 % w,
                        y: i as u32 / w,
                    })?;
                    last = (p.0, Some(c));
                    c
                }
            };
            classes.push(c);
        }
    }
    Ok(LabelMap { width: w, height: h, classes })
}

/// Class indices of label ids (row-major, rows `width` long) by `table`; an unknown id fails
/// naming `path` and the pixel.
fn classes_of_ids(ids: impl Iterator<Item = u32>, width: u32, path: &Path, table: &ClassTable) -> Result<Vec<u8>> {
    ids.enumerate()
        .map(|(i, id)| table.class_of_id(id).ok_or_else(|| Error::UnknownClassId { path: path.into(), id, x: i as u32 % width, y: i as u32 / width }))
        .collect()
}

/// A label map from label ids in memory (row-major, `width` x `height`), translated by `table`
/// as a grey label PNG is; `name` names the source in errors.
pub fn label_map_from_ids(width: u32, height: u32, ids: &[u32], name: &Path, table: &ClassTable) -> Result<LabelMap> {
    if width == 0 || height == 0 || ids.len() != width as usize * height as usize {
        return Err(Error::invalid(name.display().to_string(), format!("{} label ids for a {width}x{height} map", ids.len())));
    }
    Ok(LabelMap { width, height, classes: classes_of_ids(ids.iter().copied(), width, name, table)? })
}

/// One image to encode: an id and where its pixels and labels come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameSource {
    /// The image's id, under which a map stores it and results name it.
    pub id: String,
    /// RGB image (needed by appearance and segmentation; optional for label-only encoding).
    pub image: Option<PathBuf>,
    /// Label map; required unless a segmenter is configured.
    pub labels: Option<PathBuf>,
}

/// Loads the label map of a frame and checks it against the image size when both are given.
pub fn load_frame_labels(src: &FrameSource, table: &ClassTable, format: LabelFormat) -> Result<LabelMap> {
    let labels_path = match (&src.labels, &src.image) {
        (Some(l), _) => l,
        (None, Some(img)) => return Err(Error::NoLabels { image: img.clone() }),
        (None, None) => return Err(Error::invalid(format!("frame {:?}", src.id), "neither image nor label map given")),
    };
    let labels = load_label_map(labels_path, table, format)?;
    if let Some(img) = &src.image {
        let (iw, ih) = image_size(img)?;
        if (iw, ih) != (labels.width, labels.height) {
            return Err(Error::SizeMismatch {
                image: img.clone(),
                labels: labels_path.clone(),
                image_size: (iw, ih),
                label_size: (labels.width, labels.height),
            });
        }
    }
    Ok(labels)
}

/// Reads only an image's header to get its size.
pub fn image_size(path: &Path) -> Result<(u32, u32)> {
    let reader = image::ImageReader::open(path).map_err(|e| Error::io(path, e))?.with_guessed_format().map_err(|e| Error::io(path, e))?;
    let (w, h) = reader.into_dimensions().map_err(|e| Error::ImageDecode { path: path.into(), reason: e.to_string() })?;
    if w == 0 || h == 0 {
        return Err(Error::EmptyImage { path: path.into(), width: w, height: h });
    }
    Ok((w, h))
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{GrayImage, Luma, Rgb};

    #[test]
    fn jpegs_decode_at_the_smallest_scale_that_covers_the_request() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("f.jpg");
        let img = RgbImage::from_fn(800, 600, |x, y| Rgb([(x % 256) as u8, (y % 256) as u8, 128]));
        img.save(&p).unwrap();
        // 1/2 scale (400 x 300) covers 350 x 250; 1/4 (200 x 150) would not
        let (half, full) = load_rgb_at_least(&p, |_| (350, 250)).unwrap();
        assert_eq!((half.dimensions(), full), ((400, 300), (800, 600)));
        let (whole, _) = load_rgb_at_least(&p, |f| f).unwrap();
        assert_eq!(whole.dimensions(), (800, 600));
        // the scaled decode is a faithful small version of the image
        let small = resize_rgb(&whole, 400, 300);
        let diff: f64 = small.pixels().zip(half.pixels()).map(|(a, b)| (a.0[0] as f64 - b.0[0] as f64).abs()).sum::<f64>() / (400.0 * 300.0);
        assert!(diff < 6.0, "mean difference {diff}");
        // PNGs decode in full whatever the request
        let q = dir.path().join("f.png");
        img.save(&q).unwrap();
        assert_eq!(load_rgb_at_least(&q, |_| (10, 10)).unwrap().0.dimensions(), (800, 600));
    }

    /// A damaged header declaring 16000 x 16000 grey pixels in a 1 KB file: refused from the
    /// header, naming the file and the sizes. Before, jpeg-decoder's worker thread sized a
    /// 256 MB plane from it while the scan was decoded (4 GB for the file the long fuzz run found)
    /// and its own limit was checked only afterwards.
    #[test]
    fn a_jpeg_whose_header_declares_too_many_pixels_is_refused_before_decoding() {
        let mut bytes = Vec::new();
        let grey = GrayImage::from_fn(40, 33, |x, y| Luma([(x * y) as u8]));
        DynamicImage::ImageLuma8(grey).write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Jpeg).unwrap();
        let sof = bytes.windows(2).position(|w| w == [0xFF, 0xC0]).expect("a baseline SOF");
        // SOF0: marker, length (2), precision (1), height (2), width (2)
        bytes[sof + 5..sof + 7].copy_from_slice(&16_000u16.to_be_bytes());
        bytes[sof + 7..sof + 9].copy_from_slice(&16_000u16.to_be_bytes());
        let e = decode_rgb_at_least(bytes, Path::new("damaged.jpg"), |f| f).map(|r| r.1).unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, Error::ImageDecode { .. }) && msg.contains("damaged.jpg") && msg.contains("16000x16000") && msg.contains("MiB"), "{msg}");
        // a frame well inside the limit still decodes
        let ok = RgbImage::from_fn(1920, 1080, |x, y| Rgb([x as u8, y as u8, 7]));
        let mut b = Vec::new();
        DynamicImage::ImageRgb8(ok).write_to(&mut std::io::Cursor::new(&mut b), image::ImageFormat::Jpeg).unwrap();
        assert_eq!(decode_rgb_at_least(b, Path::new("ok.jpg"), |f| f).unwrap().1, (1920, 1080));
    }

    #[test]
    fn working_size_and_nearest_resize() {
        assert_eq!(working_size(1920, 1080, 640), (640, 360));
        assert_eq!(working_size(480, 360, 640), (480, 360), "never enlarged");
        assert_eq!(working_size(1000, 3, 100), (100, 1));
        assert_eq!(working_size(1920, 1080, 0), (1920, 1080));
        let t = ClassTable::cityscapes();
        // 4 x 2 map, left half class 0, right half class 2: halved, each side keeps its class
        let m = LabelMap::new(4, 2, vec![0, 0, 2, 2, 0, 0, 2, 2], &t).unwrap();
        assert_eq!(m.resized_nearest(2, 1).classes(), &[0, 2]);
        assert_eq!(m.resized_nearest(8, 4).resized_nearest(4, 2), m);
    }

    #[test]
    fn grey_ids_and_palette_decode() {
        let t = ClassTable::cityscapes();
        let mut g = GrayImage::new(3, 2);
        g.put_pixel(1, 0, Luma([13]));
        g.put_pixel(2, 1, Luma([255]));
        let m = decode_label_image(&DynamicImage::ImageLuma8(g), Path::new("g.png"), &t, LabelFormat::Auto).unwrap();
        assert_eq!(m.classes(), &[0, 13, 0, 0, 0, VOID]);
        let mut c = RgbImage::new(2, 1);
        c.put_pixel(0, 0, Rgb([70, 130, 180]));
        let m = decode_label_image(&DynamicImage::ImageRgb8(c), Path::new("c.png"), &t, LabelFormat::Auto).unwrap();
        assert_eq!(m.classes(), &[10, VOID]);
    }

    #[test]
    fn unknown_id_and_colour_are_named() {
        let t = ClassTable::cityscapes();
        let mut g = GrayImage::new(4, 4);
        g.put_pixel(2, 3, Luma([40]));
        let e = decode_label_image(&DynamicImage::ImageLuma8(g), Path::new("bad.png"), &t, LabelFormat::Auto).unwrap_err();
        assert!(matches!(e, Error::UnknownClassId { id: 40, x: 2, y: 3, .. }), "{e}");
        assert!(e.to_string().contains("bad.png"));
        let mut c = RgbImage::new(2, 2);
        c.put_pixel(1, 1, Rgb([1, 2, 3]));
        let e = decode_label_image(&DynamicImage::ImageRgb8(c), Path::new("col.png"), &t, LabelFormat::Auto).unwrap_err();
        assert!(matches!(e, Error::UnknownClassColor { rgb: [1, 2, 3], x: 1, y: 1, .. }), "{e}");
    }
}
