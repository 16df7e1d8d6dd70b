//! The network runtime the networks share: what runs a network and reads its weights, apart from
//! what the networks compute (each in its own module of [`crate::networks`]: XFeat, LighterGlue,
//! the embedding, the segmenter).
//!
//! - [`conv`]: the CPU operations of the convolutional networks (convolution by im2col and a
//!   matrix product, batch and instance norm, pooling, resizing), on CHW tensors.
//! - [`dense`]: the dense layers of the transformer networks (linear, softmax, layer norm, GELU).
//! - `onnx`: ONNX Runtime through `ort` (loaded dynamically), one process-wide environment and
//!   pools of sessions.
//! - `torch_pt` and `pickle`: PyTorch state dicts read without Python (the zip archive or the
//!   legacy file, its pickles run on a small safe pickle machine).

pub mod conv;
pub mod dense;
// Internal, public for the binary and tests only: ONNX Runtime loading for the command line and the tests; the networks go through `networks`.
#[doc(hidden)]
pub mod onnx;
// Internal, public for the binary and tests only: the pickle machine behind `torch_pt` and VPR-Bench's `.npy` ground truth, public for the fuzz tests only.
#[doc(hidden)]
pub mod pickle;
pub mod torch_pt;
