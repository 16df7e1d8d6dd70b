//! Inputs shared by the benchmarks: real rendered label maps of the synthetic street.
#![allow(dead_code)]

use semlook::config::Config;
use semlook::descriptors::DescriptorSet;
use semlook::descriptors::EncodedImage;
use semlook::encode::Encoder;
use semlook::input::LabelMap;
use semlook_cli::tools::synth::{self, condition::Condition, SynthConfig};

/// `n` label maps of consecutive places at `w` x `h` (degraded as under `cond`).
pub fn street_labels(n: usize, w: usize, h: usize, cond: Condition) -> Vec<LabelMap> {
    let cfg = SynthConfig { places: n, width: w, height: h, ..Default::default() };
    let scene = synth::Scene::new(&cfg);
    let dynamic = synth::world::dynamic_objects(&scene.world, cfg.seed, 0, cfg.persistence);
    let table = semlook::classes::ClassTable::cityscapes();
    (0..n)
        .map(|i| {
            let f = synth::render_frame(&cfg, &scene, &dynamic, 0, i, cond);
            LabelMap::new(w as u32, h as u32, f.labels, &table).unwrap()
        })
        .collect()
}

pub fn encode_all(cfg: &Config, maps: &[LabelMap]) -> Vec<EncodedImage> {
    let enc = Encoder::new(cfg).unwrap();
    let mut scratch = Default::default();
    maps.iter().enumerate().map(|(i, m)| enc.encode_labels(&format!("f{i}"), m, &mut scratch).unwrap().0).collect()
}

/// A map of `n` references cycling through `images` (ids made unique).
pub fn map_of(cfg: &Config, images: &[EncodedImage], n: usize) -> DescriptorSet {
    let p = cfg.global.ssim_params();
    let mut set = DescriptorSet::new(&p, cfg.local.neighbours, 0, 0);
    for i in 0..n {
        let mut img = images[i % images.len()].clone();
        img.id = format!("r{i}");
        set.push(&img).unwrap();
    }
    set
}
