//! Semantic edge extraction (CPU twin of `shaders/semantic_edges.wgsl`).
//!
//! A pixel is an edge pixel when its class takes part (not void, not excluded) and one of its
//! 4-neighbours has a different class that also takes part: the "semantic boundary pixels" of
//! `docs/design/method.md` §2.2, marked on both sides of each boundary.
//!
//! Class ids are bytes, packed four to a `u32` word (pixel i in byte i % 4 of word i / 4, little
//! endian) as the label maps hold them: the device receives one byte per pixel.

/// Bindings, in shader order: `labels` (class ids, [`pack_labels`]), `used` (256 flags), `edges`
/// (out, one per pixel). One invocation per pixel; this loop visits them in the shader's
/// global-id order. Buffers that do not hold `width` x `height` pixels panic (the shader's
/// binding contract).
pub fn semantic_edges(labels: &[u32], used: &[u32; 256], edges: &mut [u32], width: usize, height: usize) {
    assert_eq!(labels.len(), (width * height).div_ceil(4));
    assert_eq!(edges.len(), width * height);
    for y in 0..height {
        for x in 0..width {
            edges[y * width + x] = semantic_edge_at(labels, used, width, height, x, y);
        }
    }
}

/// The class of pixel `i` of packed labels (the shader's `label_at`).
#[inline]
pub fn label_at(labels: &[u32], i: usize) -> u32 {
    (labels[i >> 2] >> ((i & 3) * 8)) & 0xff
}

/// Class ids packed four to a word, as the kernel reads them (the last word zero-padded).
pub fn pack_labels(classes: &[u8], out: &mut Vec<u32>) {
    out.clear();
    out.extend(classes.chunks(4).map(|c| c.iter().enumerate().fold(0u32, |w, (k, &v)| w | (v as u32) << (8 * k))));
}

/// The per-invocation body: 1 if pixel (x, y) is a semantic boundary pixel.
#[inline]
pub fn semantic_edge_at(labels: &[u32], used: &[u32; 256], width: usize, height: usize, x: usize, y: usize) -> u32 {
    let i = y * width + x;
    let c = label_at(labels, i);
    if used[c as usize] == 0 {
        return 0;
    }
    let differs = |j: usize| {
        let n = label_at(labels, j);
        n != c && used[n as usize] != 0
    };
    let edge =
        (x > 0 && differs(i - 1)) || (x + 1 < width && differs(i + 1)) || (y > 0 && differs(i - width)) || (y + 1 < height && differs(i + width));
    edge as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packing_keeps_every_class_in_its_byte() {
        let classes: Vec<u8> = (0..11u8).map(|i| i.wrapping_mul(37)).collect();
        let mut packed = vec![];
        pack_labels(&classes, &mut packed);
        assert_eq!(packed.len(), 3);
        for (i, &c) in classes.iter().enumerate() {
            assert_eq!(label_at(&packed, i), c as u32, "pixel {i}");
        }
        // the layout the shader reads, stated independently of both functions: pixel 4w + k in
        // byte k of word w, the lowest byte first, the last word zero-padded
        pack_labels(&[0x01, 0x02, 0x03, 0x04, 0xfe], &mut packed);
        assert_eq!(packed, vec![0x0403_0201, 0x0000_00fe]);
        assert_eq!([0, 1, 2, 3, 4, 5].map(|i| label_at(&[0x0403_0201, 0x0000_00fe], i)), [1, 2, 3, 4, 0xfe, 0]);
    }
}
