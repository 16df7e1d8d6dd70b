//! The whole-image embedding run natively from its PyTorch checkpoint
//! (`networks::embedding::EfficientNetLite`, issue 61 part 1) held to the same network's ONNX graph
//! on ONNX Runtime, the product's path since sweep 16: on real frames (Cityscapes street frames,
//! Nordland winter and summer, a landmark photo) and on a synthetic image at odd sizes, the two
//! embeddings within 1 - cosine 1e-5 (both rounded to f16 as a map stores them; the largest
//! difference seen is printed). Needs the checkpoint and the graph setup.sh installs
//! (REQUIRE_MODELS=1 or CI makes their absence a failure) and, for the real frames, ../shared.

mod common;

use semlook::networks::embedding::{EfficientNetLite, Embedder};
use std::path::PathBuf;

use semlook::networks::embedding::EMBEDDING_CHECKPOINT as CHECKPOINT;
const MAX_ONE_MINUS_COSINE: f64 = 1e-5;

fn installed(name: &str) -> Option<PathBuf> {
    match semlook::nn::onnx::find_model(name, None, "embedding network") {
        Ok(p) => Some(p),
        Err(e) => {
            common::skip_unless_required("REQUIRE_MODELS", format!("{name} (run setup.sh): {e}"));
            None
        }
    }
}

fn one_minus_cosine(a: &[f32], b: &[f32]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum();
    let na: f64 = a.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    1.0 - dot / (na * nb)
}

#[test]
fn the_native_network_gives_the_graphs_embedding() {
    let (Some(ckpt), Some(graph)) = (installed(CHECKPOINT), installed(semlook::models::EMBEDDING_NETWORK)) else { return };
    let mut frames: Vec<(String, image::RgbImage, u32)> = vec![];
    // a synthetic image, at an even and at odd working sizes (TensorFlow's SAME padding differs)
    let synthetic = image::RgbImage::from_fn(447, 335, |x, y| image::Rgb(std::array::from_fn(|c| ((7 * x + 13 * y + 85 * c as u32) % 256) as u8)));
    for long in [448, 447, 335] {
        frames.push((format!("synthetic at long side {long}"), synthetic.clone(), long));
    }
    if let Some(dir) = common::shared_or_required("data") {
        for rel in [
            "street-frames/frankfurt_000000_000294_leftImg8bit.png",
            "real-vpr/nordland-spring-winter/query/001.jpg",
            "real-vpr/nordland-spring-winter/ref/001.jpg",
            "real-vpr/landmarks-multiview-dev/query/0000.jpg",
        ] {
            let img = image::open(dir.join(rel)).unwrap_or_else(|e| panic!("{rel}: {e}")).to_rgb8();
            frames.push((rel.to_string(), img, 448));
        }
    }
    let mut worst = 0.0f64;
    for (name, img, long) in &frames {
        let native = Embedder::new(&ckpt, None, *long).unwrap();
        let onnx = Embedder::new(&graph, None, *long).unwrap();
        assert_eq!((native.dim(), onnx.dim()), (1280, 1280));
        let (a, b) = (native.embed(img).unwrap(), onnx.embed(img).unwrap());
        let d = one_minus_cosine(&a, &b);
        eprintln!("{name}: 1 - cosine {d:.2e}");
        assert!(d <= MAX_ONE_MINUS_COSINE, "{name}: 1 - cosine {d:e}");
        worst = worst.max(d);
    }
    eprintln!("largest 1 - cosine over {} frames: {worst:.2e} (bound {MAX_ONE_MINUS_COSINE:e})", frames.len());
}

#[test]
fn the_checkpoint_reads_as_efficientnet_lite1() {
    let Some(ckpt) = installed(CHECKPOINT) else { return };
    // 386 tensors: 322 of floats (the 64 BatchNorms' step counters are integers, skipped)
    let sd = semlook::nn::torch_pt::read_state_dict(&ckpt).unwrap();
    assert_eq!(sd.len(), 322);
    assert_eq!(sd["_conv_stem.weight"].shape, vec![32, 3, 3, 3]);
    let net = EfficientNetLite::load(&ckpt).unwrap();
    assert_eq!(net.dim(), 1280);
    assert_eq!(format!("{net:?}"), "EfficientNetLite(21 blocks, 1280 values)");
    // too small an image is an error, not a panic
    assert!(net.forward(&semlook::nn::conv::Chw::zeros(3, 0, 4)).is_err());
}
