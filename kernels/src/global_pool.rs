//! Truncation and area resizing of the distance transform (CPU twin of `shaders/global_pool.wgsl`).
//!
//! Each output cell is the exact average of the truncated, normalised distance min(d, τ) / τ over
//! the source rectangle it covers, with fractional edge pixels weighted by their overlap: the
//! behaviour of OpenCV's INTER_AREA (`docs/design/method.md` §2.2) for any scale factor.

use super::abi::PoolParams;
/// Bindings: `params`, `d2` (squared distances), `out` (dst_width x dst_height).
/// One invocation per output cell.
pub fn global_pool(p: &PoolParams, d2: &[u32], out: &mut [f32]) {
    for oy in 0..p.dst_height {
        for ox in 0..p.dst_width {
            out[(oy * p.dst_width + ox) as usize] = global_pool_cell(p, d2, ox, oy);
        }
    }
}

/// Output cell (`ox`, `oy`), in [0, 1]: one invocation of [`global_pool`].
#[inline]
pub fn global_pool_cell(p: &PoolParams, d2: &[u32], ox: u32, oy: u32) -> f32 {
    let sx = p.src_width as f32 / p.dst_width as f32;
    let sy = p.src_height as f32 / p.dst_height as f32;
    let (x0, x1) = (ox as f32 * sx, (ox + 1) as f32 * sx);
    let (y0, y1) = (oy as f32 * sy, (oy + 1) as f32 * sy);
    let xs = x0.floor() as u32;
    let xe = (x1.ceil() as u32).min(p.src_width);
    let ys = y0.floor() as u32;
    let ye = (y1.ceil() as u32).min(p.src_height);
    let mut acc = 0.0f32;
    for y in ys..ye {
        let wy = (y1.min((y + 1) as f32) - y0.max(y as f32)).max(0.0);
        let mut row = 0.0f32;
        for x in xs..xe {
            let wx = (x1.min((x + 1) as f32) - x0.max(x as f32)).max(0.0);
            let d = (d2[(y * p.src_width + x) as usize] as f32).sqrt();
            row += wx * d.min(p.tau);
        }
        acc += wy * row;
    }
    // rounding can lift a fully truncated cell a few ulps above 1
    (acc / (sx * sy * p.tau)).min(1.0)
}

/// Reference: the same average computed in f64 from the real-valued cell bounds.
pub fn global_pool_reference(p: &PoolParams, d2: &[u32]) -> Vec<f64> {
    let (sx, sy) = (p.src_width as f64 / p.dst_width as f64, p.src_height as f64 / p.dst_height as f64);
    let tau = p.tau as f64;
    let mut out = vec![0.0; (p.dst_width * p.dst_height) as usize];
    for y in 0..p.src_height {
        for x in 0..p.src_width {
            let v = (d2[(y * p.src_width + x) as usize] as f64).sqrt().min(tau) / tau;
            // distribute pixel [x, x+1) x [y, y+1) over the cells it overlaps
            for oy in ((y as f64 / sy).floor() as u32)..(((y + 1) as f64 / sy).ceil() as u32).min(p.dst_height) {
                let wy = ((oy + 1) as f64 * sy).min((y + 1) as f64) - (oy as f64 * sy).max(y as f64);
                for ox in ((x as f64 / sx).floor() as u32)..(((x + 1) as f64 / sx).ceil() as u32).min(p.dst_width) {
                    let wx = ((ox + 1) as f64 * sx).min((x + 1) as f64) - (ox as f64 * sx).max(x as f64);
                    if wx > 0.0 && wy > 0.0 {
                        out[(oy * p.dst_width + ox) as usize] += wx * wy * v / (sx * sy);
                    }
                }
            }
        }
    }
    out
}
