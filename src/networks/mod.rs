//! The networks, one home each (as hloc's `extractors/` and `matchers/`): a network's forward
//! pass, its weights loader and, where it runs on the device, its executor live together; the
//! layers they share are [`crate::nn`]'s (CPU) and the kernels crate's (the WGSL kernels and
//! their CPU twins). The stages reach them through narrow seams: the appearance stage runs any
//! [`KeypointNetwork`] and decodes its [`NetOutputs`] itself; encoding asks an
//! [`embedding::Embedder`] for a vector and a [`segmenter::Segmenter`] for a label map;
//! verification asks [`lighterglue::LighterGlue`] for matches.
//!
//! | network | used by | CPU forward | device forward | weights |
//! |---|---|---|---|---|
//! | XFeat | appearance (VLAD), verification keypoints | [`xfeat::XFeat`] (native) | [`xfeat::XFeatGpu`] | `xfeat.pt` ([`xfeat::XFEAT_WEIGHTS`]) |
//! | any SuperPoint-layout ONNX model | appearance (`appearance.model = "onnx"`) | [`OnnxKeypoints`] (ONNX Runtime) | none | `models.keypoint_onnx` |
//! | LighterGlue | verification (`verification.matcher = "lighterglue"`) | [`lighterglue::LighterGlue`] (native) | [`lighterglue::GlueGpu`] | [`lighterglue::LIGHTERGLUE_WEIGHTS`] |
//! | EfficientNet-Lite1 + GeM | the fused coarse stage | [`embedding::Embedder`]: the ONNX graph on ONNX Runtime, or natively from the checkpoint ([`embedding::EfficientNetLite`]) | [`embedding::EmbedderGpu`] (the checkpoint's network; the GPU engine runs it where `embedding.network` names the checkpoint) | `embedding.network` |
//! | ESPNetv2 (any adapted segmenter) | labels for frames given without them | [`segmenter::Segmenter`] (ONNX Runtime) | none | [`segmenter::DEFAULT_SEGMENTER`] |
//!
//! [`crate::models`] lists the weight files by these modules' names; a new network (the device
//! path's) gets a module here beside them.

pub mod embedding;
mod keypoints;
pub mod lighterglue;
pub mod segmenter;
pub mod xfeat;

pub use keypoints::{network_input, KeypointNetwork, NetOutputs, OnnxKeypoints, MIN_NETWORK_SIDE};
