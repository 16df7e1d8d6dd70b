//! Semantic edge extraction (CPU twin of `shaders/semantic_edges.wgsl`).
//!
//! A pixel is an edge pixel when its class takes part (not void, not excluded) and one of its
//! 4-neighbours has a different class that also takes part: the "semantic boundary pixels" of spec
//! §2.2, marked on both sides of each boundary.

/// Bindings, in shader order: `labels` (one class per pixel, u32), `used` (256 flags), `edges` (out).
/// One invocation per pixel; this loop visits them in the shader's global-id order. Buffers that
/// do not hold `width` x `height` pixels panic (the shader's binding contract).
pub fn semantic_edges(labels: &[u32], used: &[u32; 256], edges: &mut [u32], width: usize, height: usize) {
    assert_eq!(labels.len(), width * height);
    assert_eq!(edges.len(), width * height);
    for y in 0..height {
        for x in 0..width {
            edges[y * width + x] = semantic_edge_at(labels, used, width, height, x, y);
        }
    }
}

/// The per-invocation body: 1 if pixel (x, y) is a semantic boundary pixel.
#[inline]
pub fn semantic_edge_at(labels: &[u32], used: &[u32; 256], width: usize, height: usize, x: usize, y: usize) -> u32 {
    let i = y * width + x;
    let c = labels[i];
    if used[c as usize] == 0 {
        return 0;
    }
    let differs = |j: usize| {
        let n = labels[j];
        n != c && used[n as usize] != 0
    };
    let edge =
        (x > 0 && differs(i - 1)) || (x + 1 < width && differs(i + 1)) || (y > 0 && differs(i - width)) || (y + 1 < height && differs(i + width));
    edge as u32
}
