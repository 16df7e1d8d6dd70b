//! A small software renderer for the synthetic street: pinhole camera, ground plane by ray
//! casting, convex polygons by scanline filling with a depth buffer, procedural materials.
//! It renders the class of every pixel and, separately, the colour; `condition` then degrades both.

use super::noise::{fbm2, hash01, value2};
use super::world::*;

pub struct Camera {
    pub pos: [f64; 3],
    pub right: [f64; 3],
    pub up: [f64; 3],
    pub fwd: [f64; 3],
    pub focal: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: usize,
    pub height: usize,
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn norm(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

const NEAR: f64 = 0.15;
/// Objects beyond this distance are not drawn.
const FAR: f64 = 260.0;

impl Camera {
    /// Camera at `pos` with yaw (radians, positive turns right) and pitch (positive up).
    pub fn new(pos: [f64; 3], yaw: f64, pitch: f64, hfov_deg: f64, width: usize, height: usize) -> Camera {
        let fwd = [yaw.sin() * pitch.cos(), pitch.sin(), yaw.cos() * pitch.cos()];
        let right = [yaw.cos(), 0.0, -yaw.sin()];
        let up = cross(fwd, right);
        let focal = (width as f64 / 2.0) / (hfov_deg.to_radians() / 2.0).tan();
        Camera { pos, right, up, fwd, focal, cx: width as f64 / 2.0, cy: height as f64 / 2.0, width, height }
    }
    fn to_cam(&self, p: [f64; 3]) -> [f64; 3] {
        let d = sub(p, self.pos);
        [dot(d, self.right), dot(d, self.up), dot(d, self.fwd)]
    }
    /// World direction of the ray through pixel centre (px, py), scaled so its depth component is 1.
    fn ray(&self, px: f64, py: f64) -> ([f64; 3], [f64; 3]) {
        let a = (px - self.cx) / self.focal;
        let b = -(py - self.cy) / self.focal;
        let cam = [a, b, 1.0];
        let world = std::array::from_fn(|i| a * self.right[i] + b * self.up[i] + self.fwd[i]);
        (cam, world)
    }
}

/// Everything the renderer produces for one frame.
pub struct Buffers {
    pub width: usize,
    pub height: usize,
    pub depth: Vec<f32>,
    pub class: Vec<u8>,
    /// What lies under thin objects (poles, signs, lights) and under far objects: the class a
    /// segmenter falls back to when it misses them.
    pub under: Vec<u8>,
    /// Class of the ground or sky at each pixel, ignoring every object.
    pub ground: Vec<u8>,
    pub color: Vec<[f32; 3]>,
    /// Emitted light (lit windows), added at night.
    pub emissive: Vec<f32>,
}

/// Lighting of a surface by normal, as the condition sets it.
pub struct Light {
    pub sun_dir: [f64; 3],
    pub sun: f32,
    pub ambient: f32,
}

fn shade(base: [f32; 3], n: [f64; 3], light: &Light) -> [f32; 3] {
    let k = light.ambient + light.sun * (dot(n, light.sun_dir).max(0.0) as f32);
    base.map(|c| c * k)
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t]
}

fn in_crossing(world: &World, z: f64) -> bool {
    world.crossings.iter().any(|&(a, b)| z >= a && z < b)
}

fn ground_kind(world: &World, side: usize, z: f64) -> GroundKind {
    let lots = &world.ground[side];
    let i = lots.partition_point(|l| l.1 <= z);
    lots.get(i).filter(|l| l.0 <= z).map_or(GroundKind::Terrain, |l| l.2)
}

/// Class and base colour of the ground at world (x, z).
fn ground_at(world: &World, x: f64, z: f64, seed: u64) -> (u8, [f32; 3]) {
    let ax = x.abs();
    let grain = hash01((x * 20.0).floor() as i64, (z * 20.0).floor() as i64, 7, seed) - 0.5;
    if ax < ROAD_HALF || in_crossing(world, z) {
        let mut c = [0.22 + 0.05 * grain, 0.22 + 0.05 * grain, 0.23 + 0.05 * grain];
        let dash = (z / 6.0).rem_euclid(1.0) < 0.5;
        let centre = x.abs() < 0.08 && dash && !in_crossing(world, z);
        let edge = (ax - (ROAD_HALF - 1.7)).abs() < 0.06 && !in_crossing(world, z);
        let zebra = world.crossings.iter().any(|&(a, _)| z >= a && z < a + 3.0) && ax < ROAD_HALF && (x / 0.6).rem_euclid(1.0) < 0.5;
        if centre || edge || zebra {
            c = [0.8, 0.8, 0.78];
        }
        (ROAD, c)
    } else if ax < SIDEWALK_OUTER {
        let tile = ((x / 0.5).rem_euclid(1.0) < 0.04) || ((z / 0.5).rem_euclid(1.0) < 0.04);
        let v = if tile { 0.42 } else { 0.58 + 0.06 * grain };
        (SIDEWALK, [v, v * 0.98, v * 0.95])
    } else {
        let side = (x > 0.0) as usize;
        match ground_kind(world, side, z) {
            GroundKind::Paved => (SIDEWALK, [0.52 + 0.05 * grain, 0.51, 0.49]),
            GroundKind::Terrain => {
                let n = fbm2(x * 0.7, z * 0.7, seed ^ 3);
                (TERRAIN, [0.25 + 0.2 * n + 0.08 * grain, 0.38 + 0.15 * n, 0.15 + 0.05 * grain])
            }
        }
    }
}

/// Base colour of a material at texture coordinates (s, h) and world point `p`; the second value
/// is its emitted light at night.
fn material_color(m: &Material, s: f64, h: f64, p: [f64; 3], seed: u64) -> ([f32; 3], f32) {
    let grain = |scale: f64| hash01((s * scale).floor() as i64, (h * scale).floor() as i64, 11, seed) - 0.5;
    match m {
        Material::Plain { color, grain: g } => (color.map(|c| (c * (1.0 + g * grain(25.0))).max(0.0)), 0.0),
        Material::Blocks { color } => {
            let row = (h / 0.25).floor();
            let off = if row as i64 % 2 == 0 { 0.0 } else { 0.25 };
            let joint = (h / 0.25).rem_euclid(1.0) < 0.08 || ((s + off) / 0.5).rem_euclid(1.0) < 0.05;
            (if joint { color.map(|c| c * 0.6) } else { color.map(|c| c * (1.0 + 0.15 * grain(30.0))) }, 0.0)
        }
        Material::Facade(st) => facade(st, s, h, seed),
        Material::Leaves { color, seed: ls } => {
            let n = hash01((p[0] * 6.0).floor() as i64, (p[1] * 6.0).floor() as i64, (p[2] * 6.0).floor() as i64, *ls);
            let m = value2(p[0] * 1.3 + p[2], p[1] * 1.3, *ls);
            (color.map(|c| c * (0.55 + 0.6 * n + 0.3 * m)), 0.0)
        }
        Material::Sign { bg, fg, shape } => {
            let (u, v) = (s - 0.0, h);
            let size = 0.6;
            let (cu, cv) = (u / size - 0.5, v / size - 0.5);
            let inner = match shape {
                0 => cu * cu + cv * cv < 0.09,
                1 => cv.abs() < 0.12,
                _ => (cu.abs() + cv.abs()) < 0.3,
            };
            (if inner { *fg } else { *bg }, 0.0)
        }
        Material::TrafficLight => {
            let lamp = [0.2, 0.5, 0.8].iter().any(|&c| ((h - c * 1.0) / 0.12).powi(2) + ((s - 0.2) / 0.12).powi(2) < 1.0);
            if lamp {
                ([0.9, 0.6, 0.1], 1.0)
            } else {
                ([0.05, 0.05, 0.05], 0.0)
            }
        }
        Material::CarBody { color } => (color.map(|c| c * (1.0 + 0.05 * grain(10.0))), 0.0),
        Material::Person { top, bottom } => (if h > 0.45 { *top } else { *bottom }, 0.0),
        Material::Fence { color } => {
            let bar = (s / 0.15).rem_euclid(1.0) < 0.35 || h.rem_euclid(1.0) > 0.9;
            (if bar { *color } else { color.map(|c| c * 0.45) }, 0.0)
        }
    }
}

fn facade(st: &FacadeStyle, s: f64, h: f64, seed: u64) -> ([f32; 3], f32) {
    let g = hash01((s * 12.0).floor() as i64, (h * 12.0).floor() as i64, st.id as i64, seed) - 0.5;
    let wall = st.wall.map(|c| c * (1.0 + 0.12 * g));
    if h < st.shop_h {
        // shop front: large windows with a coloured band and door
        let bay = (s / (st.spacing * 2.0)).rem_euclid(1.0);
        if h > st.shop_h - 0.6 {
            return (st.shop, 0.0);
        }
        if h > 0.4 && bay > 0.1 && bay < 0.85 {
            let lit = hash01((s / (st.spacing * 2.0)).floor() as i64, -1, st.id as i64, seed) > 0.3;
            return (st.glass.map(|c| c * 1.3), if lit { 0.9 } else { 0.0 });
        }
        return (wall.map(|c| c * 0.85), 0.0);
    }
    let hh = h - st.shop_h;
    let floor = (hh / st.floor_h).floor();
    let fy = hh - floor * st.floor_h;
    let col = (s / st.spacing).floor();
    let mut fx = s - col * st.spacing;
    if st.pattern == 3 {
        fx = (fx * 2.0).rem_euclid(st.spacing);
    }
    let wx0 = (st.spacing - st.win_w) / 2.0;
    let wy0 = (st.floor_h - st.win_h) / 2.0;
    let in_win = fx > wx0 && fx < wx0 + st.win_w && fy > wy0 && fy < wy0 + st.win_h;
    let in_frame = fx > wx0 - 0.08 && fx < wx0 + st.win_w + 0.08 && fy > wy0 - 0.08 && fy < wy0 + st.win_h + 0.08;
    if in_win {
        let lit = hash01(col as i64, floor as i64, st.id as i64, seed) > 0.55;
        let shade = 0.8 + 0.4 * hash01(col as i64, floor as i64, st.id as i64 + 7, seed);
        return (st.glass.map(|c| c * shade), if lit { 1.0 } else { 0.0 });
    }
    if in_frame {
        return (st.frame, 0.0);
    }
    match st.pattern {
        1 if fy < 0.25 => (wall.map(|c| c * 0.7), 0.0),
        2 if fx < 0.2 => (wall.map(|c| c * 1.2), 0.0),
        _ => (wall, 0.0),
    }
}

impl Buffers {
    pub fn new(width: usize, height: usize) -> Buffers {
        let n = width * height;
        Buffers {
            width,
            height,
            depth: vec![f32::INFINITY; n],
            class: vec![SKY; n],
            under: vec![SKY; n],
            ground: vec![SKY; n],
            color: vec![[0.0; 3]; n],
            emissive: vec![0.0; n],
        }
    }
}

/// Sky colour of a pixel (top to horizon gradient with soft clouds).
pub fn sky_color(dir: [f64; 3], top: [f32; 3], horizon: [f32; 3], seed: u64) -> [f32; 3] {
    let d = norm(dir);
    let t = (d[1].max(0.0) * 2.5).min(1.0) as f32;
    let base = mix(horizon, top, t);
    let cloud = fbm2(d[0] / (d[1] + 0.1) * 2.0, d[2] / (d[1] + 0.1) * 2.0, seed ^ 99);
    let c = ((cloud - 0.55) * 3.0).clamp(0.0, 1.0) * 0.5;
    mix(base, [0.9, 0.9, 0.92], c)
}

/// Renders the ground and sky (every pixel), then every primitive.
pub fn render(world: &World, prims: &[&Prim], cam: &Camera, light: &Light, sky: ([f32; 3], [f32; 3]), seed: u64) -> Buffers {
    let mut buf = Buffers::new(cam.width, cam.height);
    for py in 0..cam.height {
        for px in 0..cam.width {
            let i = py * cam.width + px;
            let (_, dir) = cam.ray(px as f64 + 0.5, py as f64 + 0.5);
            if dir[1] < -1e-6 {
                let t = -cam.pos[1] / dir[1];
                let (x, z) = (cam.pos[0] + t * dir[0], cam.pos[2] + t * dir[2]);
                let (class, base) = ground_at(world, x, z, seed);
                buf.class[i] = class;
                buf.under[i] = class;
                buf.ground[i] = class;
                buf.depth[i] = t as f32;
                buf.color[i] = shade(base, [0.0, 1.0, 0.0], light);
            } else {
                buf.color[i] = sky_color(dir, sky.0, sky.1, seed);
            }
        }
    }
    for prim in prims {
        draw(&mut buf, prim, cam, light, seed);
    }
    buf
}

fn draw(buf: &mut Buffers, prim: &Prim, cam: &Camera, light: &Light, seed: u64) {
    // world polygon, texture origin and axes
    let (poly, origin, s_axis, h_axis): (Vec<[f64; 3]>, [f64; 3], [f64; 3], [f64; 3]) = match &prim.shape {
        Shape::Quad(c) => (c.to_vec(), c[0], norm(sub(c[1], c[0])), norm(sub(c[3], c[0]))),
        Shape::Disc { center, radius } => {
            let to_cam = norm(sub(cam.pos, *center));
            let r = norm(cross([0.0, 1.0, 0.0], to_cam));
            let u = cross(to_cam, r);
            let pts = (0..14)
                .map(|k| {
                    let a = k as f64 / 14.0 * std::f64::consts::TAU;
                    let wob = 1.0 + 0.12 * ((a * 3.0 + center[0]).sin());
                    std::array::from_fn(|i| center[i] + radius * wob * (a.cos() * r[i] + a.sin() * u[i]))
                })
                .collect();
            (pts, *center, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        }
        Shape::Billboard { base, width, height } => {
            let to_cam = sub(cam.pos, *base);
            let r = norm(cross([to_cam[0], 0.0, to_cam[2]], [0.0, 1.0, 0.0]));
            let hw = width / 2.0;
            let c0 = [base[0] - hw * r[0], 0.0, base[2] - hw * r[2]];
            let c1 = [base[0] + hw * r[0], 0.0, base[2] + hw * r[2]];
            let pts = vec![c0, c1, [c1[0], *height, c1[2]], [c0[0], *height, c0[2]]];
            (pts, c0, r, [0.0, 1.0 / height, 0.0])
        }
    };
    let centre = poly.iter().fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]]).map(|v| v / poly.len() as f64);
    // Outward normal of a quad: h x s (x right, y up, z forward is a left-handed frame).
    // Discs and billboards always face the camera.
    let normal = match prim.shape {
        Shape::Quad(_) => norm(cross(sub(poly[poly.len() - 1], poly[0]), sub(poly[1], poly[0]))),
        _ => norm(sub(cam.pos, centre)),
    };
    // back-face culling (the depth test alone would be correct; this halves the work on boxes)
    if dot(normal, sub(cam.pos, centre)) <= 0.0 {
        return;
    }
    let cam_pts: Vec<[f64; 3]> = poly.iter().map(|&p| cam.to_cam(p)).collect();
    if cam_pts.iter().all(|p| p[2] > FAR) {
        return;
    }
    let clipped = clip_near(&cam_pts);
    if clipped.len() < 3 {
        return;
    }
    let proj: Vec<[f64; 2]> = clipped.iter().map(|p| [cam.cx + cam.focal * p[0] / p[2], cam.cy - cam.focal * p[1] / p[2]]).collect();
    let (ymin, ymax) = proj.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p[1]), b.max(p[1])));
    let (xmin, xmax) = proj.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p[0]), b.max(p[0])));
    if ymax < 0.0 || xmax < 0.0 || ymin > cam.height as f64 || xmin > cam.width as f64 {
        return;
    }
    let n_cam = cam.to_cam_dir(normal);
    let d_plane = dot(n_cam, clipped[0]);
    let py0 = ((ymin - 0.5).ceil().max(0.0)) as usize;
    let py1 = ((ymax - 0.5).floor().min(cam.height as f64 - 1.0)) as i64;
    for py in py0 as i64..=py1 {
        let y = py as f64 + 0.5;
        let (mut xl, mut xr) = (f64::MAX, f64::MIN);
        for k in 0..proj.len() {
            let (a, b) = (proj[k], proj[(k + 1) % proj.len()]);
            if (a[1] <= y && b[1] > y) || (b[1] <= y && a[1] > y) {
                let x = a[0] + (y - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
                xl = xl.min(x);
                xr = xr.max(x);
            }
        }
        if xl > xr {
            continue;
        }
        let px0 = (xl - 0.5).ceil().max(0.0) as usize;
        let px1 = (xr - 0.5).floor().min(cam.width as f64 - 1.0);
        if px1 < 0.0 {
            continue;
        }
        for px in px0..=(px1 as usize) {
            let (rc, rw) = cam.ray(px as f64 + 0.5, y);
            let denom = dot(n_cam, rc);
            if denom.abs() < 1e-12 {
                continue;
            }
            let t = d_plane / denom;
            let i = py as usize * cam.width + px;
            if t <= NEAR || t as f32 >= buf.depth[i] {
                continue;
            }
            let p: [f64; 3] = std::array::from_fn(|k| cam.pos[k] + t * rw[k]);
            let rel = sub(p, origin);
            let (s, h) = (dot(rel, s_axis), dot(rel, h_axis));
            let (base, emit) = material_color(&prim.material, s, h, p, seed);
            if prim.thin {
                buf.under[i] = buf.class[i];
            } else {
                buf.under[i] = prim.class;
            }
            buf.depth[i] = t as f32;
            buf.class[i] = prim.class;
            buf.color[i] = shade(base, normal, light);
            buf.emissive[i] = emit;
        }
    }
}

impl Camera {
    fn to_cam_dir(&self, d: [f64; 3]) -> [f64; 3] {
        [dot(d, self.right), dot(d, self.up), dot(d, self.fwd)]
    }
}

/// Sutherland-Hodgman clipping of a camera-space polygon against z >= NEAR.
fn clip_near(poly: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let mut out = Vec::with_capacity(poly.len() + 2);
    for k in 0..poly.len() {
        let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
        let (ina, inb) = (a[2] >= NEAR, b[2] >= NEAR);
        if ina {
            out.push(a);
        }
        if ina != inb {
            let t = (NEAR - a[2]) / (b[2] - a[2]);
            out.push(std::array::from_fn(|i| a[i] + t * (b[i] - a[i])));
        }
    }
    out
}
