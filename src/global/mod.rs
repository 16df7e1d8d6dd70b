//! Whole-image descriptors: one vector per image, compared whole (a cosine or an SSIM), what the
//! coarse stage ranks the map by and what the baselines are.
//!
//! - The SemLook global descriptor ([`encode_global`]; "Edge (Coarse)", `docs/design/method.md`
//!   §2.2): semantic edges -> exact distance transform -> small map compared by SSIM
//!   ([`ssim_fast`] is its fast CPU path).
//! - [`vlad`]: the VLAD of an image's appearance descriptors with the map's codebook (setting
//!   `appearance`, and `fused`'s first term).
//! - the learned whole-image embedding (`fused`'s second term) is a network: [`crate::networks::embedding`].
//! - [`hog`]: VPR-Bench's HOG baseline (setting `hog`; the compact HOG of small frames).
//!
//! How they are ranked is `matching`'s (`matching::baseline` for the baselines, the coarse
//! stage for `fused`).

pub mod hog;
mod semantic;
pub mod ssim_fast;
pub mod vlad;

pub use semantic::{encode_global, pool_params, GlobalScratch};
