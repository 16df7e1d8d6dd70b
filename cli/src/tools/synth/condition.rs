//! Capture conditions: how a traversal's light, weather and camera change the picture, and how
//! they degrade the label map the way a real segmenter degrades (lost far and thin objects,
//! wobbly boundaries, confused classes under snow and at night).

use super::noise::{hash01, value2};
use super::render::{Buffers, Light};
use super::world::*;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Condition {
    Day,
    Overcast,
    Sunset,
    Fog,
    Night,
    Snow,
}

impl Condition {
    pub fn name(self) -> &'static str {
        match self {
            Condition::Day => "day",
            Condition::Overcast => "overcast",
            Condition::Sunset => "sunset",
            Condition::Fog => "fog",
            Condition::Night => "night",
            Condition::Snow => "snow",
        }
    }
}

/// Numeric description of a condition.
pub struct Params {
    pub light: Light,
    pub sky_top: [f32; 3],
    pub sky_horizon: [f32; 3],
    pub tint: [f32; 3],
    pub exposure: f32,
    /// Fog colour and the distance at which fog hides 95 % of a surface (m); None: clear.
    pub fog: Option<([f32; 3], f32)>,
    pub emissive: f32,
    /// Headlight gain on near surfaces (night).
    pub headlight: f32,
    pub noise: f32,
    pub snow: f32,
    /// Label degradation: boundary jitter amplitude (px), visibility of objects and of thin
    /// objects (m), fraction of area with confused classes.
    pub wobble_px: f32,
    pub visibility: f32,
    pub thin_visibility: f32,
    pub confusion: f32,
}

pub fn params(c: Condition) -> Params {
    let sun = |x: f64, y: f64, z: f64| {
        let n = (x * x + y * y + z * z).sqrt();
        [x / n, y / n, z / n]
    };
    match c {
        Condition::Day => Params {
            light: Light { sun_dir: sun(0.4, 0.8, -0.3), sun: 0.55, ambient: 0.6 },
            sky_top: [0.25, 0.45, 0.85],
            sky_horizon: [0.7, 0.8, 0.95],
            tint: [1.0, 1.0, 1.0],
            exposure: 1.05,
            fog: None,
            emissive: 0.0,
            headlight: 0.0,
            noise: 0.01,
            snow: 0.0,
            wobble_px: 1.0,
            visibility: 1e9,
            thin_visibility: 90.0,
            confusion: 0.0,
        },
        Condition::Overcast => Params {
            light: Light { sun_dir: sun(0.0, 1.0, 0.0), sun: 0.15, ambient: 0.75 },
            sky_top: [0.62, 0.64, 0.68],
            sky_horizon: [0.78, 0.79, 0.8],
            tint: [0.95, 0.97, 1.0],
            exposure: 0.9,
            fog: Some(([0.7, 0.72, 0.74], 400.0)),
            emissive: 0.0,
            headlight: 0.0,
            noise: 0.015,
            snow: 0.0,
            wobble_px: 1.5,
            visibility: 200.0,
            thin_visibility: 70.0,
            confusion: 0.01,
        },
        Condition::Sunset => Params {
            light: Light { sun_dir: sun(-0.9, 0.15, 0.4), sun: 0.8, ambient: 0.35 },
            sky_top: [0.3, 0.3, 0.55],
            sky_horizon: [0.98, 0.6, 0.3],
            tint: [1.15, 0.85, 0.6],
            exposure: 0.85,
            fog: Some(([0.9, 0.6, 0.4], 600.0)),
            emissive: 0.3,
            headlight: 0.0,
            noise: 0.02,
            snow: 0.0,
            wobble_px: 2.0,
            visibility: 140.0,
            thin_visibility: 55.0,
            confusion: 0.02,
        },
        Condition::Fog => Params {
            light: Light { sun_dir: sun(0.0, 1.0, 0.0), sun: 0.1, ambient: 0.8 },
            sky_top: [0.78, 0.79, 0.8],
            sky_horizon: [0.8, 0.81, 0.82],
            tint: [0.97, 0.98, 1.0],
            exposure: 0.95,
            fog: Some(([0.8, 0.81, 0.82], 70.0)),
            emissive: 0.0,
            headlight: 0.0,
            noise: 0.02,
            snow: 0.0,
            wobble_px: 2.5,
            visibility: 45.0,
            thin_visibility: 25.0,
            confusion: 0.04,
        },
        Condition::Night => Params {
            light: Light { sun_dir: sun(0.0, 1.0, 0.0), sun: 0.0, ambient: 0.16 },
            sky_top: [0.01, 0.015, 0.04],
            sky_horizon: [0.05, 0.05, 0.09],
            tint: [0.9, 0.9, 1.1],
            exposure: 1.0,
            fog: Some(([0.02, 0.02, 0.04], 140.0)),
            emissive: 0.9,
            headlight: 2.5,
            noise: 0.05,
            snow: 0.0,
            wobble_px: 3.5,
            visibility: 40.0,
            thin_visibility: 20.0,
            confusion: 0.08,
        },
        Condition::Snow => Params {
            light: Light { sun_dir: sun(0.2, 1.0, 0.0), sun: 0.2, ambient: 0.85 },
            sky_top: [0.85, 0.86, 0.88],
            sky_horizon: [0.9, 0.9, 0.92],
            tint: [0.95, 0.98, 1.05],
            exposure: 1.0,
            fog: Some(([0.88, 0.89, 0.9], 160.0)),
            emissive: 0.0,
            headlight: 0.0,
            noise: 0.03,
            snow: 0.75,
            wobble_px: 2.5,
            visibility: 80.0,
            thin_visibility: 35.0,
            confusion: 0.07,
        },
    }
}

fn confuse(class: u8, c: Condition, h: f32) -> u8 {
    match (c, class) {
        (Condition::Snow, ROAD | SIDEWALK) => TERRAIN,
        (Condition::Snow, TERRAIN) => SIDEWALK,
        (Condition::Snow, VEGETATION) => TERRAIN,
        (Condition::Night, SKY) => BUILDING,
        (Condition::Night, BUILDING) => {
            if h < 0.5 {
                SKY
            } else {
                VEGETATION
            }
        }
        (Condition::Night, VEGETATION) => BUILDING,
        (Condition::Night, SIDEWALK) => ROAD,
        (Condition::Fog, VEGETATION) => BUILDING,
        (Condition::Fog, BUILDING) => SKY,
        (_, SIDEWALK) => ROAD,
        (_, TERRAIN) => VEGETATION,
        (_, VEGETATION) => TERRAIN,
        (_, WALL) => BUILDING,
        (_, FENCE) => WALL,
        (_, other) => other,
    }
}

/// The label map a segmenter would output under condition `c`.
pub fn degrade_labels(buf: &Buffers, c: Condition, p: &Params, seed: u64) -> Vec<u8> {
    let (w, h) = (buf.width, buf.height);
    let mut seen = buf.class.clone();
    for i in 0..w * h {
        let d = buf.depth[i];
        let cls = seen[i];
        if cls == SKY || cls == ROAD || cls == SIDEWALK || cls == TERRAIN {
            continue;
        }
        if d > p.visibility {
            seen[i] = buf.ground[i];
        } else if matches!(cls, POLE | TRAFFIC_SIGN | TRAFFIC_LIGHT) && d > p.thin_visibility {
            seen[i] = buf.under[i];
        }
    }
    if p.confusion > 0.0 {
        let threshold = 1.0 - p.confusion * 2.2;
        for y in 0..h {
            for x in 0..w {
                let n = value2(x as f64 / 45.0, y as f64 / 45.0, seed ^ 0xC0);
                if n > threshold {
                    let i = y * w + x;
                    seen[i] = confuse(seen[i], c, hash01(x as i64 / 40, y as i64 / 40, 5, seed));
                }
            }
        }
    }
    // boundary wobble: read each label from a smoothly displaced position
    let amp = p.wobble_px as f64;
    let mut out = vec![SKY; w * h];
    for y in 0..h {
        for x in 0..w {
            let dx = amp * (2.0 * value2(x as f64 / 17.0, y as f64 / 17.0, seed ^ 0xA1) as f64 - 1.0);
            let dy = amp * (2.0 * value2(x as f64 / 17.0, y as f64 / 17.0, seed ^ 0xB2) as f64 - 1.0);
            let sx = (x as f64 + dx).round().clamp(0.0, w as f64 - 1.0) as usize;
            let sy = (y as f64 + dy).round().clamp(0.0, h as f64 - 1.0) as usize;
            out[y * w + x] = seen[sy * w + sx];
        }
    }
    out
}

/// The 8-bit RGB picture under condition `c`.
pub fn develop(buf: &Buffers, p: &Params, seed: u64) -> Vec<u8> {
    let (w, h) = (buf.width, buf.height);
    let mut out = Vec::with_capacity(w * h * 3);
    for i in 0..w * h {
        let mut c = buf.color[i];
        let cls = buf.class[i];
        if p.snow > 0.0 {
            let (x, y) = (i % w, i / w);
            let cover = match cls {
                ROAD => 0.55,
                SIDEWALK | TERRAIN => 0.9,
                VEGETATION => 0.45,
                _ => 0.0,
            } * p.snow;
            if cover > 0.0 {
                let n = value2(x as f64 / 9.0, y as f64 / 9.0, seed ^ 0x5E);
                c = mix3(c, [0.92, 0.93, 0.96], (cover * (0.6 + 0.4 * n)).min(1.0));
            }
            if hash01(x as i64, y as i64, 17, seed) < 0.004 {
                c = [1.0, 1.0, 1.0];
            }
        }
        c = [c[0] * p.tint[0] * p.exposure, c[1] * p.tint[1] * p.exposure, c[2] * p.tint[2] * p.exposure];
        if p.emissive > 0.0 && buf.emissive[i] > 0.0 {
            let e = p.emissive * buf.emissive[i];
            c = [c[0] + e * 0.95, c[1] + e * 0.8, c[2] + e * 0.45];
        }
        if p.headlight > 0.0 && cls != SKY {
            let k = 1.0 + p.headlight * (-buf.depth[i] / 18.0).exp();
            c = c.map(|v| v * k);
        }
        if let Some((fog, dist)) = p.fog {
            let d = buf.depth[i].min(1e6);
            let f = if cls == SKY { 0.85 } else { 1.0 - (-3.0 * d / dist).exp() };
            c = mix3(c, fog, f);
        }
        let (x, y) = (i % w, i / w);
        let nz = (hash01(x as i64, y as i64, 23, seed) - 0.5) * 2.0 * p.noise * 1.7;
        for v in c {
            let g = (v.max(0.0) + nz).clamp(0.0, 1.0).powf(1.0 / 1.6);
            out.push((g * 255.0 + 0.5) as u8);
        }
    }
    out
}

fn mix3(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t]
}
