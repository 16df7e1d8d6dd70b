//! The synthetic benchmark: one procedural street route, driven several times under different
//! conditions, written in a SYNTHIA-like layout (RGB images, Cityscapes train-id label maps,
//! CameraParams poses) with a `semlook-dataset.json` that pairs the reference traversal with the
//! query traversals. Fully deterministic from the seed.
//!
//! What makes it hard: blocks repeat a few layout templates along the route (perceptual
//! aliasing); query traversals drive with lateral, longitudinal, yaw and pitch offsets; parked
//! cars and pedestrians change between traversals; and each condition degrades the label maps as
//! a segmenter would (far and thin objects lost, boundaries jittered, classes confused).

pub mod camvid;
pub mod condition;
mod noise;
pub mod render;
pub mod stream;
pub mod world;

use condition::Condition;
use rayon::prelude::*;
use semlook::dataset::{write_synthia_pose, DatasetManifest, GroundTruthRule, Pose, TraversalSpec, MANIFEST, SYNTHIA_CAMERA};
use semlook::error::{Error, Result};
use semlook::util::SplitMix64;
use serde::{Deserialize, Serialize};
use std::path::Path;
pub use world::dynamic_objects;
use world::{Prim, Shape, World};

/// Camera offsets from the place positions, drawn uniformly in +-value.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Jitter {
    pub lateral_m: f64,
    pub along_m: f64,
    pub yaw_deg: f64,
    pub pitch_deg: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SynthConfig {
    pub seed: u64,
    /// Places along the route (frames per traversal).
    pub places: usize,
    /// Distance between places (m).
    pub spacing_m: f64,
    pub width: usize,
    pub height: usize,
    pub hfov_deg: f64,
    pub reference: Condition,
    pub queries: Vec<Condition>,
    /// Probability that a block repeats one of three layout templates.
    pub aliasing: f64,
    /// Fraction of parked cars that stay between traversals.
    pub persistence: f64,
    pub reference_jitter: Jitter,
    pub query_jitter: Jitter,
    /// Ground truth: references within this distance of a query are correct (m).
    pub gt_distance_m: f64,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            seed: 7,
            places: 150,
            spacing_m: 5.0,
            width: 640,
            height: 480,
            hfov_deg: 80.0,
            reference: Condition::Day,
            queries: vec![Condition::Overcast, Condition::Sunset, Condition::Fog, Condition::Snow, Condition::Night],
            aliasing: 0.6,
            persistence: 0.4,
            reference_jitter: Jitter { lateral_m: 0.2, along_m: 0.3, yaw_deg: 1.0, pitch_deg: 0.5 },
            query_jitter: Jitter { lateral_m: 0.9, along_m: 2.0, yaw_deg: 6.0, pitch_deg: 2.0 },
            gt_distance_m: 7.0,
        }
    }
}

/// Bytes the in-memory world takes per metre of route: 1.67 primitives per metre of 144 bytes
/// each plus boxed facade styles and culling extents, about 260 bytes (measured with
/// `build_world(7, 5000 m, 0.6)`), rounded up for other seeds and aliasing.
const WORLD_BYTES_PER_METRE: f64 = 400.0;
/// The share of the machine's available memory the world may take (frames are rendered and
/// written one per thread beside it).
const WORLD_MEMORY_SHARE: f64 = 0.5;

impl SynthConfig {
    /// Bytes the route's world will hold in memory.
    pub fn world_bytes(&self) -> f64 {
        (self.places as f64 * self.spacing_m + 320.0) * WORLD_BYTES_PER_METRE
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |r: String| Err(Error::invalid("synth config", r));
        if self.places == 0 || self.width < 64 || self.height < 48 || self.width > 4096 || self.height > 4096 {
            return bad(format!("need places >= 1 and a size from 64x48 to 4096x4096, got {} places at {}x{}", self.places, self.width, self.height));
        }
        let budget = semlook::util::available_memory_bytes() as f64 * WORLD_MEMORY_SHARE;
        if self.world_bytes() > budget {
            return bad(format!(
                "{} places would need about {:.1} GiB for the world alone; this machine can give it {:.1} GiB (half of its available memory): ask for at most {} places",
                self.places,
                self.world_bytes() / 1073741824.0,
                budget / 1073741824.0,
                ((budget / WORLD_BYTES_PER_METRE - 320.0) / self.spacing_m.max(1e-9)).max(0.0) as u64
            ));
        }
        let nums = [self.spacing_m, self.hfov_deg, self.aliasing, self.persistence, self.gt_distance_m];
        if nums.iter().any(|v| !v.is_finite() || *v < 0.0) || self.spacing_m == 0.0 || self.hfov_deg >= 170.0 {
            return bad("spacing, field of view, aliasing, persistence and gt distance must be finite and positive".into());
        }
        if self.queries.is_empty() || self.queries.contains(&self.reference) {
            return bad("query conditions must be non-empty and differ from the reference".into());
        }
        Ok(())
    }
}

/// A rendered frame: RGB bytes, class ids (train ids), and the camera pose.
pub struct RenderedFrame {
    pub rgb: Vec<u8>,
    pub labels: Vec<u8>,
    pub clean_labels: Vec<u8>,
    pub pose: Pose,
}

/// The route's static world plus per-primitive z extents for culling.
pub struct Scene {
    pub world: World,
    extents: Vec<(f64, f64)>,
}

impl Scene {
    pub fn new(cfg: &SynthConfig) -> Scene {
        let world = world::build_world(cfg.seed, cfg.places as f64 * cfg.spacing_m, cfg.aliasing);
        let extents = world.prims.iter().map(z_extent).collect();
        Scene { world, extents }
    }
}

fn z_extent(p: &Prim) -> (f64, f64) {
    match &p.shape {
        Shape::Quad(c) => c.iter().fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v[2]), b.max(v[2]))),
        Shape::Disc { center, radius } => (center[2] - radius, center[2] + radius),
        Shape::Billboard { base, width, .. } => (base[2] - width, base[2] + width),
    }
}

/// Renders frame `place` of traversal `traversal` (0 = reference) under `cond`.
pub fn render_frame(cfg: &SynthConfig, scene: &Scene, dynamic: &[Prim], traversal: u64, place: usize, cond: Condition) -> RenderedFrame {
    let jit = if traversal == 0 { cfg.reference_jitter } else { cfg.query_jitter };
    let mut rng = SplitMix64::derive(cfg.seed, (traversal << 32) | place as u64);
    let z = place as f64 * cfg.spacing_m + jit.along_m * rng.range(-1.0, 1.0);
    let x = world::LANE_X + jit.lateral_m * rng.range(-1.0, 1.0);
    let yaw = (jit.yaw_deg * rng.range(-1.0, 1.0)).to_radians();
    let pitch = (jit.pitch_deg * rng.range(-1.0, 1.0)).to_radians();
    let cam = render::Camera::new([x, 1.6, z], yaw, pitch, cfg.hfov_deg, cfg.width, cfg.height);
    let frame_key = (traversal << 32) | place as u64;
    let traffic = world::traffic_near(z, cfg.seed, frame_key);
    let visible = |ext: (f64, f64)| ext.1 > z - 40.0 && ext.0 < z + 270.0;
    let mut prims: Vec<&Prim> = scene.world.prims.iter().zip(&scene.extents).filter(|(_, e)| visible(**e)).map(|(p, _)| p).collect();
    prims.extend(dynamic.iter().filter(|p| visible(z_extent(p))));
    prims.extend(traffic.iter());
    let p = condition::params(cond);
    let buf = render::render(&scene.world, &prims, &cam, &p.light, (p.sky_top, p.sky_horizon), cfg.seed ^ traversal.wrapping_mul(0x1234_5678));
    let frame_seed = cfg.seed ^ frame_key.wrapping_mul(0x9E37_79B9);
    RenderedFrame {
        rgb: condition::develop(&buf, &p, frame_seed),
        labels: condition::degrade_labels(&buf, cond, &p, frame_seed),
        clean_labels: buf.class.clone(),
        pose: Pose { position: cam.pos, forward: cam.fwd, orientation: None },
    }
}

fn write_png(path: &Path, data: &[u8], w: usize, h: usize, color: image::ExtendedColorType) -> Result<()> {
    use image::ImageEncoder;
    let f = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    let enc = image::codecs::png::PngEncoder::new_with_quality(
        std::io::BufWriter::new(f),
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Sub,
    );
    enc.write_image(data, w as u32, h as u32, color).map_err(|e| Error::ImageDecode { path: path.into(), reason: e.to_string() })
}

/// Generates the whole dataset into `out`; `tick` is called once per written frame.
pub fn generate(cfg: &SynthConfig, out: &Path, tick: &(dyn Fn() + Sync)) -> Result<()> {
    cfg.validate()?;
    let scene = Scene::new(cfg);
    let conditions: Vec<Condition> = std::iter::once(cfg.reference).chain(cfg.queries.iter().copied()).collect();
    for (t, cond) in conditions.iter().enumerate() {
        let base = out.join(cond.name());
        for sub in ["RGB", "GT/LABELS", "CameraParams"] {
            let d = base.join(sub).join(SYNTHIA_CAMERA);
            std::fs::create_dir_all(&d).map_err(|e| Error::io(&d, e))?;
        }
        let dynamic = world::dynamic_objects(&scene.world, cfg.seed, t as u64, cfg.persistence);
        (0..cfg.places).into_par_iter().try_for_each(|i| -> Result<()> {
            let f = render_frame(cfg, &scene, &dynamic, t as u64, i, *cond);
            let name = format!("{i:06}");
            write_png(
                &base.join("RGB").join(SYNTHIA_CAMERA).join(format!("{name}.png")),
                &f.rgb,
                cfg.width,
                cfg.height,
                image::ExtendedColorType::Rgb8,
            )?;
            write_png(
                &base.join("GT/LABELS").join(SYNTHIA_CAMERA).join(format!("{name}.png")),
                &f.labels,
                cfg.width,
                cfg.height,
                image::ExtendedColorType::L8,
            )?;
            let pose_path = base.join("CameraParams").join(SYNTHIA_CAMERA).join(format!("{name}.txt"));
            std::fs::write(&pose_path, write_synthia_pose(&f.pose)).map_err(|e| Error::io(&pose_path, e))?;
            tick();
            Ok(())
        })?;
    }
    let manifest = DatasetManifest {
        format: "semlook-dataset".into(),
        version: 1,
        name: Some(format!("synth-seed{}", cfg.seed)),
        layout: "synthia".into(),
        camera: None,
        label_format: semlook::input::LabelFormat::Auto,
        label_ids: Some(semlook::config::LabelIds::Named("train_id".into())),
        reference: TraversalSpec::Named(cfg.reference.name().into()),
        queries: cfg.queries.iter().map(|c| TraversalSpec::Named(c.name().into())).collect(),
        ground_truth: Some(GroundTruthRule { max_distance: cfg.gt_distance_m, max_angle_deg: None }),
    };
    let mpath = out.join(MANIFEST);
    std::fs::write(&mpath, serde_json::to_vec_pretty(&manifest).map_err(|e| Error::invalid("dataset manifest", e.to_string()))?)
        .map_err(|e| Error::io(&mpath, e))?;
    let spath = out.join("synth.json");
    std::fs::write(&spath, serde_json::to_vec_pretty(cfg).map_err(|e| Error::invalid("synth config", e.to_string()))?)
        .map_err(|e| Error::io(&spath, e))?;
    Ok(())
}
