//! Stage 0b: label maps from RGB images with an ONNX segmentation network, for frames given
//! without a label map. The adapter (`[segmentation]` in the config) says how to feed the
//! network (input size, scale, mean and std per channel, RGB or BGR) and what each output channel
//! means (a class of the table, or "void"): logits -> argmax -> class -> nearest-neighbour resize
//! back to the image size. Defaults fit ESPNet's Cityscapes export (19 classes + ignore).

use crate::classes::{ClassTable, VOID};
use crate::config::SegmentationConfig;
use crate::error::{Error, Result};
use crate::input::LabelMap;
use image::RgbImage;
use std::path::{Path, PathBuf};

/// File name of the default segmenter in the model folders: ESPNetv2 (Mehta et al., CVPR 2019)
/// trained on Cityscapes, which `setup.sh` installs when it can. Chosen over ESPNet for real
/// streets: CamVid mIoU 60.2 vs 36.6, and faster (see `../shared/models/README.md`).
pub const DEFAULT_SEGMENTER: &str = "espnetv2_cityscapes.onnx";

/// An ONNX segmentation network with its adapter (`[segmentation]`): RGB images in, label maps out.
pub struct Segmenter {
    sessions: crate::nn::onnx::SessionPool,
    cfg: SegmentationConfig,
    class_of_channel: Vec<u8>,
    path: PathBuf,
    /// The network takes any batch size (first input dimension dynamic).
    dynamic_batch: bool,
    sha256: String,
}

impl std::fmt::Debug for Segmenter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Segmenter({})", self.path.display())
    }
}

/// Dark-frame normalisation before segmentation: when the mean grey level of `img` (in [0, 1])
/// is below `target`, a gamma curve that brings the mean to `target` (x -> x^g with
/// g = ln(target) / ln(mean)); otherwise, or with `target` 0, the identity. As a lookup table
/// over 8-bit values.
pub fn brighten_lut(img: &RgbImage, target: f64) -> [f32; 256] {
    let mut lut: [f32; 256] = std::array::from_fn(|v| v as f32);
    if target <= 0.0 || img.is_empty() {
        return lut;
    }
    let n = img.pixels().len() as f64;
    let mean = img.pixels().map(|p| (p.0[0] as f64 + p.0[1] as f64 + p.0[2] as f64) / 765.0).sum::<f64>() / n;
    if mean >= target || mean <= 0.0 {
        return lut;
    }
    let g = target.ln() / mean.ln();
    for (v, slot) in lut.iter_mut().enumerate() {
        *slot = (255.0 * (v as f64 / 255.0).powf(g)) as f32;
    }
    lut
}

impl Segmenter {
    /// Loads the network at `path` (`onnxruntime`: `models.onnxruntime`, see
    /// [`crate::nn::onnx::library_path`]); fails if `cfg.class_map` names a class `table` lacks, or
    /// does not name one class per output channel.
    pub fn load(path: &Path, cfg: &SegmentationConfig, table: &ClassTable, onnxruntime: Option<&Path>) -> Result<Segmenter> {
        let class_of_channel = cfg
            .class_map
            .iter()
            .map(|n| {
                if n == "void" {
                    Ok(VOID)
                } else {
                    table.index(n).ok_or_else(|| Error::InvalidConfig {
                        source_name: "[segmentation]".into(),
                        reason: format!("class_map names {n:?}, which is not in the class table"),
                    })
                }
            })
            .collect::<Result<Vec<u8>>>()?;
        let sessions = crate::nn::onnx::SessionPool::new(path, onnxruntime)?;
        let (outputs, inputs) = sessions.with_shared(|s| (s.outputs().len(), s.inputs().len()));
        if outputs == 0 || inputs == 0 {
            return Err(Error::Model {
                path: path.into(),
                reason: format!("{inputs} inputs and {outputs} outputs; a segmenter has an image input and a logits output"),
            });
        }
        let channels = sessions.with_shared(|s| crate::nn::onnx::output_shape(s, 0)).get(1).copied().unwrap_or(-1);
        if channels > 0 && channels as usize != class_of_channel.len() {
            return Err(Error::Model {
                path: path.into(),
                reason: format!("{channels} output channels, but segmentation.class_map names {}", class_of_channel.len()),
            });
        }
        let dynamic_batch = sessions.with_shared(|s| match s.inputs().first().map(|i| i.dtype()) {
            Some(ort::value::ValueType::Tensor { shape, .. }) => shape.first().is_some_and(|&d| d < 0),
            _ => false,
        });
        Ok(Segmenter { sessions, cfg: cfg.clone(), class_of_channel, path: path.into(), dynamic_batch, sha256: crate::util::sha256_file(path)? })
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        &self.path
    }
    /// SHA-256 of the model file.
    pub fn sha256(&self) -> &str {
        &self.sha256
    }

    /// Label map of one image at its own size; `name` names the image in errors.
    pub fn segment(&self, rgb: &RgbImage, name: &Path) -> Result<LabelMap> {
        self.segment_to(rgb, name, (rgb.width(), rgb.height()))
    }

    /// Label map of one image at `size` (the network's output resized by nearest neighbour).
    pub fn segment_to(&self, rgb: &RgbImage, name: &Path, size: (u32, u32)) -> Result<LabelMap> {
        let mut maps = self.segment_batch_to(&[rgb], &[size]).map_err(|e| match e {
            Error::Model { reason, .. } => Error::Model { path: self.path.clone(), reason: format!("segmenting {}: {reason}", name.display()) },
            other => other,
        })?;
        maps.pop().ok_or_else(|| Error::Model { path: self.path.clone(), reason: "no output".into() })
    }

    /// Label maps of several images at their own sizes: one network call when the network
    /// takes batches, else one call per image.
    pub fn segment_batch(&self, images: &[&RgbImage]) -> Result<Vec<LabelMap>> {
        let sizes: Vec<(u32, u32)> = images.iter().map(|i| (i.width(), i.height())).collect();
        self.segment_batch_to(images, &sizes)
    }

    /// Label maps of several images, each at its size in `sizes`.
    pub fn segment_batch_to(&self, images: &[&RgbImage], sizes: &[(u32, u32)]) -> Result<Vec<LabelMap>> {
        if images.len() != sizes.len() {
            return Err(Error::invalid("segmenter", "one output size per image"));
        }
        if !self.dynamic_batch && images.len() > 1 {
            let one = |(i, s): (&&RgbImage, &(u32, u32))| -> Result<LabelMap> {
                self.segment_batch_to(std::slice::from_ref(i), std::slice::from_ref(s))?
                    .pop()
                    .ok_or_else(|| Error::Model { path: self.path.clone(), reason: "no output".into() })
            };
            return images.iter().zip(sizes).map(one).collect();
        }
        let (w, h) = (self.cfg.input_width, self.cfg.input_height);
        let n = images.len();
        let mut input = vec![0.0f32; n * 3 * h * w];
        for (b, img) in images.iter().enumerate() {
            if img.width() == 0 || img.height() == 0 {
                return Err(Error::invalid("image", "empty image"));
            }
            let small = image::imageops::resize(*img, w as u32, h as u32, image::imageops::FilterType::Triangle);
            let lut = brighten_lut(&small, self.cfg.brighten_dark);
            for (i, p) in small.pixels().enumerate() {
                for c in 0..3 {
                    let src = if self.cfg.bgr { 2 - c } else { c };
                    input[((b * 3 + c) * h * w) + i] = ((lut[p.0[src] as usize] as f64 * self.cfg.scale - self.cfg.mean[c]) / self.cfg.std[c]) as f32;
                }
            }
        }
        let fail = |reason: String| Error::Model { path: self.path.clone(), reason };
        let (shape, logits) = self.sessions.run(|session| {
            let tensor = ort::value::TensorRef::from_array_view(([n, 3, h, w], input.as_slice())).map_err(|e| fail(e.to_string()))?;
            let outputs = session.run(ort::inputs![tensor]).map_err(|e| fail(e.to_string()))?;
            let value = outputs.values().next().ok_or_else(|| fail("the model returned no output".into()))?;
            let (shape, logits) = value.try_extract_tensor::<f32>().map_err(|e| fail(format!("output 0: {e}")))?;
            Ok((shape.to_vec(), logits.to_vec()))
        })?;
        let c = self.class_of_channel.len();
        let wrong = || fail(format!("output shape {shape:?}, expected [{n}, {c}, h, w] (segmentation.class_map names {c} channels)"));
        let [b, ch, oh, ow] = shape[..] else { return Err(wrong()) };
        let (Ok(oh), Ok(ow)) = (usize::try_from(oh), usize::try_from(ow)) else { return Err(wrong()) };
        if b != n as i64 || ch != c as i64 || oh == 0 || ow == 0 || oh > u32::MAX as usize || ow > u32::MAX as usize {
            return Err(wrong());
        }
        if n.checked_mul(c).and_then(|v| v.checked_mul(oh)).and_then(|v| v.checked_mul(ow)) != Some(logits.len()) {
            return Err(fail(format!("output holds {} values for shape {shape:?}", logits.len())));
        }
        let mut maps = Vec::with_capacity(n);
        for (b, &(tw, th)) in sizes.iter().enumerate() {
            let plane = &logits[b * c * oh * ow..(b + 1) * c * oh * ow];
            let mut small = vec![VOID; oh * ow];
            for (i, slot) in small.iter_mut().enumerate() {
                let mut best = (f32::NEG_INFINITY, 0usize);
                for ch in 0..c {
                    let v = plane[ch * oh * ow + i];
                    if v > best.0 {
                        best = (v, ch);
                    }
                }
                *slot = self.class_of_channel.get(best.1).copied().unwrap_or(VOID);
            }
            if tw == 0 || th == 0 {
                return Err(Error::invalid("segmenter", "empty output size"));
            }
            maps.push(LabelMap::from_classes_unchecked(ow as u32, oh as u32, small).resized_nearest(tw, th));
        }
        Ok(maps)
    }
}
