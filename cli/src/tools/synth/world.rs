//! The procedural street: a straight road along +z with sidewalks, built from blocks of "lots"
//! (buildings, parks, walls, parking) and street furniture, separated by cross streets. Blocks are
//! drawn from a few layout templates, so the semantic layout repeats along the route (perceptual
//! aliasing), while every building gets its own facade (colour, window grid, shop front), so
//! appearance can tell repeated layouts apart. Dynamic objects (cars, people) are drawn per
//! traversal, a fraction of parked cars staying in place.

use semlook::util::SplitMix64;

// Cityscapes train ids used by the generator.
pub const ROAD: u8 = 0;
pub const SIDEWALK: u8 = 1;
pub const BUILDING: u8 = 2;
pub const WALL: u8 = 3;
pub const FENCE: u8 = 4;
pub const POLE: u8 = 5;
pub const TRAFFIC_LIGHT: u8 = 6;
pub const TRAFFIC_SIGN: u8 = 7;
pub const VEGETATION: u8 = 8;
pub const TERRAIN: u8 = 9;
pub const SKY: u8 = 10;
pub const PERSON: u8 = 11;
pub const CAR: u8 = 13;

/// Road half width (two lanes and parking strips), sidewalk outer edge, lane centre of the camera.
pub const ROAD_HALF: f64 = 5.0;
pub const SIDEWALK_OUTER: f64 = 8.0;
pub const LANE_X: f64 = 1.7;

#[derive(Debug, Clone, PartialEq)]
pub struct FacadeStyle {
    pub id: u64,
    pub wall: [f32; 3],
    pub glass: [f32; 3],
    pub frame: [f32; 3],
    pub shop: [f32; 3],
    pub floor_h: f64,
    pub win_w: f64,
    pub win_h: f64,
    pub spacing: f64,
    pub shop_h: f64,
    /// 0 plain grid, 1 horizontal bands, 2 vertical pilasters, 3 paired windows.
    pub pattern: u8,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Material {
    Facade(Box<FacadeStyle>),
    Plain { color: [f32; 3], grain: f32 },
    Blocks { color: [f32; 3] },
    Leaves { color: [f32; 3], seed: u64 },
    Sign { bg: [f32; 3], fg: [f32; 3], shape: u8 },
    TrafficLight,
    CarBody { color: [f32; 3] },
    Person { top: [f32; 3], bottom: [f32; 3] },
    Fence { color: [f32; 3] },
}

/// A renderable primitive.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    /// Planar convex quad, corners in order; (s, h) texture axes along c0->c1 and c0->c3.
    Quad([[f64; 3]; 4]),
    /// Disc of `radius` around `center`, always facing the camera (tree crowns, bushes).
    Disc { center: [f64; 3], radius: f64 },
    /// Upright rectangle standing at `base`, turned to face the camera (people).
    Billboard { base: [f64; 3], width: f64, height: f64 },
}

#[derive(Debug, Clone, PartialEq)]
pub struct Prim {
    pub shape: Shape,
    pub class: u8,
    pub material: Material,
    /// Thin objects (poles, signs, lights) that a segmenter misses at distance.
    pub thin: bool,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GroundKind {
    Terrain,
    Paved,
}

#[derive(Debug, Clone)]
pub struct World {
    pub prims: Vec<Prim>,
    /// z ranges of cross streets.
    pub crossings: Vec<(f64, f64)>,
    /// Per side (0 left, 1 right): (z0, z1, ground kind beyond the sidewalk).
    pub ground: [Vec<(f64, f64, GroundKind)>; 2],
    pub z_min: f64,
    pub z_max: f64,
}

#[derive(Debug, Clone)]
enum LotKind {
    Building { height: f64, depth: f64, setback: f64 },
    Park { trees: Vec<(f64, f64, f64)> }, // (dz, x offset, size)
    Wall { height: f64 },
    Parking,
}

#[derive(Debug, Clone)]
struct Lot {
    z0: f64,
    z1: f64,
    kind: LotKind,
}

#[derive(Debug, Clone)]
struct Furniture {
    z: f64,
    side: usize,
    /// 0 sign pole, 1 street lamp, 2 sidewalk tree
    kind: u8,
    size: f64,
}

#[derive(Debug, Clone)]
struct BlockTemplate {
    length: f64,
    lots: [Vec<Lot>; 2],
    furniture: Vec<Furniture>,
}

fn hsv(h: f64, s: f64, v: f64) -> [f32; 3] {
    let i = (h * 6.0).floor();
    let f = h * 6.0 - i;
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - f * s), v * (1.0 - (1.0 - f) * s));
    let (r, g, b) = match i as i64 % 6 {
        0 => (v, t, p),
        1 => (q, v, p),
        2 => (p, v, t),
        3 => (p, q, v),
        4 => (t, p, v),
        _ => (v, p, q),
    };
    [r as f32, g as f32, b as f32]
}

fn random_block(rng: &mut SplitMix64) -> BlockTemplate {
    let length = rng.range(60.0, 100.0);
    let mut lots: [Vec<Lot>; 2] = [vec![], vec![]];
    for side_lots in lots.iter_mut() {
        let mut z = 0.0;
        while z < length - 6.0 {
            let w = rng.range(9.0, 26.0).min(length - z);
            let r = rng.next_f64();
            let kind = if r < 0.62 {
                LotKind::Building { height: rng.range(7.0, 26.0), depth: rng.range(10.0, 18.0), setback: rng.range(0.0, 2.5) }
            } else if r < 0.8 {
                let n = 1 + rng.below(3);
                LotKind::Park { trees: (0..n).map(|_| (rng.range(1.5, w - 1.5), rng.range(2.0, 9.0), rng.range(0.8, 1.3))).collect() }
            } else if r < 0.92 {
                LotKind::Wall { height: rng.range(1.2, 2.6) }
            } else {
                LotKind::Parking
            };
            side_lots.push(Lot { z0: z, z1: z + w, kind });
            z += w;
        }
    }
    let mut furniture = Vec::new();
    for side in 0..2 {
        let mut z = rng.range(2.0, 14.0);
        while z < length - 2.0 {
            let kind = match rng.below(10) {
                0..=3 => 0,
                4..=6 => 1,
                _ => 2,
            };
            furniture.push(Furniture { z, side, kind, size: rng.range(0.85, 1.2) });
            z += rng.range(9.0, 24.0);
        }
    }
    BlockTemplate { length, lots, furniture }
}

/// Jitters a template's geometry slightly (a repeated block is similar, not identical).
fn perturb(t: &BlockTemplate, rng: &mut SplitMix64, amount: f64) -> BlockTemplate {
    let mut t = t.clone();
    for lots in t.lots.iter_mut() {
        for lot in lots.iter_mut() {
            if let LotKind::Building { height, setback, .. } = &mut lot.kind {
                *height *= 1.0 + amount * rng.range(-1.0, 1.0);
                *setback = (*setback + amount * rng.range(-1.0, 1.0)).max(0.0);
            }
        }
    }
    for f in t.furniture.iter_mut() {
        f.z = (f.z + amount * 4.0 * rng.range(-1.0, 1.0)).clamp(1.0, t.length - 1.0);
    }
    t
}

fn facade_style(rng: &mut SplitMix64, id: u64) -> FacadeStyle {
    let hue = rng.next_f64();
    let glass_hue = 0.5 + rng.range(-0.15, 0.15);
    FacadeStyle {
        id,
        wall: hsv(hue, rng.range(0.08, 0.55), rng.range(0.35, 0.9)),
        glass: hsv(glass_hue, rng.range(0.1, 0.5), rng.range(0.08, 0.35)),
        frame: if rng.chance(0.5) { [0.9, 0.9, 0.88] } else { hsv(rng.next_f64(), 0.3, rng.range(0.1, 0.4)) },
        shop: hsv(rng.next_f64(), rng.range(0.3, 0.9), rng.range(0.3, 0.9)),
        floor_h: rng.range(2.9, 3.8),
        win_w: rng.range(0.7, 1.7),
        win_h: rng.range(1.0, 1.9),
        spacing: rng.range(1.9, 3.6),
        shop_h: rng.range(3.2, 4.6),
        pattern: rng.below(4) as u8,
    }
}

fn quad(c: [[f64; 3]; 4], class: u8, material: Material) -> Prim {
    Prim { shape: Shape::Quad(c), class, material, thin: false }
}

/// An axis-aligned box as its vertical faces (roofs are never seen from street level).
#[allow(clippy::too_many_arguments)]
fn box_faces(x0: f64, x1: f64, z0: f64, z1: f64, y0: f64, y1: f64, class: u8, front: Material, side: Material, thin: bool) -> Vec<Prim> {
    let mk = |c, m: Material| Prim { shape: Shape::Quad(c), class, material: m, thin };
    vec![
        mk([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]], side.clone()), // faces -z
        mk([[x1, y0, z1], [x0, y0, z1], [x0, y1, z1], [x1, y1, z1]], side.clone()), // faces +z
        mk([[x0, y0, z1], [x0, y0, z0], [x0, y1, z0], [x0, y1, z1]], front.clone()), // faces -x
        mk([[x1, y0, z0], [x1, y0, z1], [x1, y1, z1], [x1, y1, z0]], front),        // faces +x
        mk([[x0, y1, z0], [x1, y1, z0], [x1, y1, z1], [x0, y1, z1]], side),         // top (low boxes: cars, walls)
    ]
}

fn tree(prims: &mut Vec<Prim>, x: f64, z: f64, size: f64, rng: &mut SplitMix64) {
    let trunk_h = 2.2 * size + rng.range(0.0, 1.0);
    let bark = Material::Plain { color: [0.25, 0.18, 0.12], grain: 0.3 };
    prims.extend(box_faces(x - 0.15, x + 0.15, z - 0.15, z + 0.15, 0.0, trunk_h, VEGETATION, bark.clone(), bark, false));
    let r = rng.range(1.4, 2.6) * size;
    let green = hsv(rng.range(0.2, 0.36), rng.range(0.45, 0.8), rng.range(0.22, 0.5));
    prims.push(Prim {
        shape: Shape::Disc { center: [x, trunk_h + r * 0.8, z], radius: r },
        class: VEGETATION,
        material: Material::Leaves { color: green, seed: rng.next_u64() },
        thin: false,
    });
}

fn pole_with(prims: &mut Vec<Prim>, x: f64, z: f64, height: f64, rng: &mut SplitMix64, sign: bool) {
    let metal = Material::Plain { color: [0.45, 0.46, 0.47], grain: 0.05 };
    prims.extend(box_faces(x - 0.08, x + 0.08, z - 0.08, z + 0.08, 0.0, height, POLE, metal.clone(), metal, true));
    if sign {
        let palette = [[0.8, 0.1, 0.1], [0.1, 0.25, 0.8], [0.95, 0.8, 0.1], [0.1, 0.55, 0.2], [0.95, 0.95, 0.95]];
        let bg = palette[rng.below(palette.len())];
        let fg = palette[rng.below(palette.len())];
        let s = rng.range(0.5, 0.8);
        let y = rng.range(2.0, 2.8);
        prims.push(Prim {
            shape: Shape::Quad([[x - s / 2.0, y, z - 0.1], [x + s / 2.0, y, z - 0.1], [x + s / 2.0, y + s, z - 0.1], [x - s / 2.0, y + s, z - 0.1]]),
            class: TRAFFIC_SIGN,
            material: Material::Sign { bg, fg, shape: rng.below(3) as u8 },
            thin: true,
        });
    }
}

fn traffic_light(prims: &mut Vec<Prim>, x: f64, z: f64, rng: &mut SplitMix64) {
    pole_with(prims, x, z, 3.2, rng, false);
    let y = 3.2;
    prims.extend(box_faces(x - 0.2, x + 0.2, z - 0.25, z - 0.05, y, y + 1.0, TRAFFIC_LIGHT, Material::TrafficLight, Material::TrafficLight, true));
}

/// Builds the static world for a route of `length` metres (camera z from 0 to `length`).
pub fn build_world(seed: u64, length: f64, aliasing: f64) -> World {
    let mut rng = SplitMix64::derive(seed, 1);
    let n_templates = 3;
    let templates: Vec<BlockTemplate> = (0..n_templates).map(|_| random_block(&mut rng)).collect();
    let mut prims = Vec::new();
    let mut crossings = Vec::new();
    let mut ground: [Vec<(f64, f64, GroundKind)>; 2] = [vec![], vec![]];
    let z_min = -60.0;
    let z_max = length + 260.0;
    let mut z = z_min;
    let mut style_id = 0u64;
    while z < z_max {
        let block = if rng.chance(aliasing) { perturb(&templates[rng.below(n_templates)], &mut rng, 0.08) } else { random_block(&mut rng) };
        for (side, lots) in block.lots.iter().enumerate() {
            let sgn = if side == 0 { -1.0 } else { 1.0 };
            for lot in lots {
                let (z0, z1) = (z + lot.z0, z + lot.z1);
                let kind = match &lot.kind {
                    LotKind::Building { height, depth, setback } => {
                        let style = facade_style(&mut rng, style_id);
                        style_id += 1;
                        let xf = SIDEWALK_OUTER + setback;
                        let (x0, x1) = if side == 0 { (-xf - depth, -xf) } else { (xf, xf + depth) };
                        let side_mat = Material::Plain { color: style.wall.map(|c| c * 0.8), grain: 0.15 };
                        prims.extend(box_faces(
                            x0,
                            x1,
                            z0 + 0.2,
                            z1 - 0.2,
                            0.0,
                            *height,
                            BUILDING,
                            Material::Facade(Box::new(style)),
                            side_mat,
                            false,
                        ));
                        GroundKind::Paved
                    }
                    LotKind::Park { trees } => {
                        for &(dz, dx, size) in trees {
                            tree(&mut prims, sgn * (SIDEWALK_OUTER + dx), z0 + dz.min(lot.z1 - lot.z0 - 0.5), size, &mut rng);
                        }
                        if rng.chance(0.5) {
                            let h = rng.range(0.9, 1.4);
                            let x = sgn * (SIDEWALK_OUTER + 0.2);
                            // facing the road: towards +x on the left side, -x on the right
                            let c = if side == 0 {
                                [[x, 0.0, z0], [x, 0.0, z1], [x, h, z1], [x, h, z0]]
                            } else {
                                [[x, 0.0, z1], [x, 0.0, z0], [x, h, z0], [x, h, z1]]
                            };
                            prims.push(quad(c, FENCE, Material::Fence { color: hsv(rng.next_f64(), 0.2, rng.range(0.2, 0.7)) }));
                        }
                        GroundKind::Terrain
                    }
                    LotKind::Wall { height } => {
                        let x = sgn * (SIDEWALK_OUTER + 0.3);
                        let (x0, x1) = if side == 0 { (x - 0.3, x) } else { (x, x + 0.3) };
                        let concrete = Material::Blocks { color: hsv(rng.range(0.05, 0.15), rng.range(0.0, 0.25), rng.range(0.45, 0.75)) };
                        prims.extend(box_faces(x0, x1, z0, z1, 0.0, *height, WALL, concrete.clone(), concrete, false));
                        if rng.chance(0.7) {
                            tree(&mut prims, sgn * (SIDEWALK_OUTER + rng.range(3.0, 7.0)), (z0 + z1) / 2.0, 1.0, &mut rng);
                        }
                        GroundKind::Terrain
                    }
                    LotKind::Parking => GroundKind::Paved,
                };
                ground[side].push((z0, z1, kind));
            }
        }
        for f in &block.furniture {
            let sgn = if f.side == 0 { -1.0 } else { 1.0 };
            let zf = z + f.z;
            match f.kind {
                0 => pole_with(&mut prims, sgn * (ROAD_HALF + 0.5), zf, 3.2 * f.size, &mut rng, true),
                1 => {
                    pole_with(&mut prims, sgn * (ROAD_HALF + 0.4), zf, 7.0 * f.size, &mut rng, false);
                    let metal = Material::Plain { color: [0.4, 0.41, 0.42], grain: 0.05 };
                    let (xa, xb) = if f.side == 0 { (-ROAD_HALF - 0.4, -ROAD_HALF + 1.2) } else { (ROAD_HALF - 1.2, ROAD_HALF + 0.4) };
                    let y = 7.0 * f.size;
                    prims.extend(box_faces(xa, xb, zf - 0.08, zf + 0.08, y - 0.15, y, POLE, metal.clone(), metal, true));
                }
                _ => tree(&mut prims, sgn * (ROAD_HALF + 1.4), zf, f.size * 0.9, &mut rng),
            }
        }
        z += block.length;
        // cross street
        let width = rng.range(11.0, 16.0);
        crossings.push((z, z + width));
        for side in 0..2 {
            let sgn = if side == 0 { -1.0 } else { 1.0 };
            traffic_light(&mut prims, sgn * (ROAD_HALF + 0.6), z - 0.5, &mut rng);
            if rng.chance(0.5) {
                pole_with(&mut prims, sgn * (ROAD_HALF + 0.6), z + width + 1.0, 3.0, &mut rng, true);
            }
        }
        z += width;
    }
    World { prims, crossings, ground, z_min, z_max }
}

/// Dynamic objects of one traversal: parked cars (a `persistence` fraction shared by all
/// traversals) and pedestrians.
pub fn dynamic_objects(world: &World, seed: u64, traversal: u64, persistence: f64) -> Vec<Prim> {
    let mut shared = SplitMix64::derive(seed, 2);
    let mut own = SplitMix64::derive(seed, 1000 + traversal);
    let mut prims = Vec::new();
    for side in 0..2 {
        let sgn = if side == 0 { -1.0 } else { 1.0 };
        let mut z = world.z_min;
        while z < world.z_max {
            let (occupied_shared, color_shared) = (shared.chance(0.45), shared.next_f64());
            let keep = own.chance(persistence);
            let (occupied, color) = if keep { (occupied_shared, color_shared) } else { (own.chance(0.45), own.next_f64()) };
            let in_crossing = world.crossings.iter().any(|&(a, b)| z + 5.0 > a - 2.0 && z < b + 2.0);
            if occupied && !in_crossing {
                car(&mut prims, sgn * (ROAD_HALF - 0.95), z + 0.6, color, side == 0);
            }
            z += 6.0;
        }
        let n_people = ((world.z_max - world.z_min) / 12.0) as usize;
        for _ in 0..n_people {
            let z = own.range(world.z_min, world.z_max);
            let x = sgn * own.range(ROAD_HALF + 0.8, SIDEWALK_OUTER - 0.4);
            let h = own.range(1.55, 1.9);
            prims.push(Prim {
                shape: Shape::Billboard { base: [x, 0.0, z], width: 0.55, height: h },
                class: PERSON,
                material: Material::Person {
                    top: hsv(own.next_f64(), 0.6, own.range(0.2, 0.9)),
                    bottom: hsv(own.next_f64(), 0.3, own.range(0.1, 0.5)),
                },
                thin: false,
            });
        }
    }
    prims
}

/// A car as two boxes (body and cabin), `x` its centre, `z` its rear.
pub fn car(prims: &mut Vec<Prim>, x: f64, z: f64, hue: f64, _left: bool) {
    let body = Material::CarBody { color: hsv(hue, 0.6, 0.25 + 0.6 * ((hue * 7.0) % 1.0)) };
    let (hw, len) = (0.88, 4.3);
    prims.extend(box_faces(x - hw, x + hw, z, z + len, 0.25, 1.0, CAR, body.clone(), body.clone(), false));
    let glass = Material::Plain { color: [0.06, 0.07, 0.09], grain: 0.05 };
    prims.extend(box_faces(x - hw + 0.1, x + hw - 0.1, z + 1.1, z + 3.3, 1.0, 1.45, CAR, glass.clone(), glass, false));
}

/// Cars driving in the lanes near one frame (they differ from frame to frame).
pub fn traffic_near(cam_z: f64, seed: u64, frame: u64) -> Vec<Prim> {
    let mut rng = SplitMix64::derive(seed, 50_000 + frame);
    let mut prims = Vec::new();
    for _ in 0..rng.below(4) {
        let lane = if rng.chance(0.5) { LANE_X } else { -LANE_X };
        car(&mut prims, lane, cam_z + rng.range(9.0, 70.0), rng.next_f64(), lane < 0.0);
    }
    prims
}
