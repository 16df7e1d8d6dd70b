//! The LighterGlue fixtures (tests/data/lighterglue_pairs.json, written once by
//! scripts/make_lighterglue_fixtures.py): real pairs' keypoints as the map stores them and the
//! authors' model's matches. Shared by tests/lighterglue.rs and tests/gpu/lighterglue.rs.

use semlook::descriptors::keypoints::KeypointsRef;
use semlook::networks::lighterglue::{LighterGlue, LIGHTERGLUE_WEIGHTS};
use serde_json::Value;

/// One image's stored keypoints.
pub struct Stored {
    pub xy: Vec<u16>,
    pub descriptors: Vec<i8>,
    pub classes: Vec<u8>,
}

impl Stored {
    /// The keypoints of `image` (image0 or image1) of a fixture pair.
    pub fn of(pair: &Value, image: &str) -> Stored {
        let xy: Vec<u16> = pair[format!("{image}_xy")].as_array().unwrap().iter().map(|v| v.as_u64().unwrap() as u16).collect();
        let b64 = pair[format!("{image}_descriptors_b64")].as_str().unwrap();
        let descriptors: Vec<i8> = base64_decode(b64).into_iter().map(|b| b as i8).collect();
        assert_eq!(descriptors.len(), xy.len() / 2 * 64);
        Stored { classes: vec![0; xy.len() / 2], xy, descriptors }
    }
    /// As the matcher takes them.
    pub fn as_ref(&self) -> KeypointsRef<'_> {
        KeypointsRef { descriptors: &self.descriptors, xy: &self.xy, classes: &self.classes, dim: 64 }
    }
}

fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let bytes: Vec<u8> = s.bytes().filter(|&c| c != b'=').collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let v: Vec<u32> = chunk.iter().map(|&c| val(c) as u32).collect();
        let n = v.iter().enumerate().fold(0u32, |a, (i, &x)| a | x << (18 - 6 * i));
        out.extend((0..chunk.len() - 1).map(|i| (n >> (16 - 8 * i)) as u8));
    }
    out
}

/// The fixture file.
pub fn fixtures() -> Value {
    serde_json::from_str(&std::fs::read_to_string(super::repo().join("tests/data/lighterglue_pairs.json")).unwrap()).unwrap()
}

/// The reference's matches of a fixture pair's run ("pruned" or "full"): (i, j, probability).
pub fn reference_matches(pair: &Value, run: &str) -> Vec<(u32, u32, f32)> {
    let r = &pair[run];
    r["matches0"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
        .filter_map(|(i, j)| {
            let j = j.as_i64().unwrap();
            (j >= 0).then(|| (i as u32, j as u32, r["scores0"][i].as_f64().unwrap() as f32))
        })
        .collect()
}

/// The LighterGlue weights setup.sh installs, loaded; without them the test skips with the reason
/// (or fails under CI or REQUIRE_MODELS=1) and should return.
pub fn network() -> Option<LighterGlue> {
    match semlook::nn::onnx::find_model(LIGHTERGLUE_WEIGHTS, None, "LighterGlue") {
        Ok(path) => Some(LighterGlue::load(&path).unwrap()),
        Err(e) => {
            super::skip_unless_required("REQUIRE_MODELS", format!("LighterGlue weights (run setup.sh): {e}"));
            None
        }
    }
}
