//! A map split into shards of contiguous segments, for matching spread over several processes or
//! machines (the Python package's Ray driver): [`plan`] cuts a manifest into balanced ranges,
//! [`Map::open_range`] opens one range alone (only its segment files are read), [`Map::open_header`]
//! what a driver that holds no segment file needs to encode queries. A shard's
//! reference `i` is the map's reference `global_start + i`, so per-shard candidate lists merge
//! into exactly the lists of one process ([`crate::matching::merge_lists`]).

use super::{manifest, Manifest, Map};
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::path::Path;

/// One shard: a range of the manifest's segments, the map index of its first live image, its
/// live images, and the generation it was planned at.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardSpec {
    /// Range of the manifest's segments.
    pub segments: Range<usize>,
    /// Map index of the shard's first live image.
    pub global_start: usize,
    /// Live images of the shard.
    pub len: usize,
    /// Manifest generation the shard was planned at.
    pub generation: u64,
}

/// Cuts the map into `shards` contiguous ranges of segments with about equal live images (each
/// range at least one segment). Fails if the map has fewer segments than `shards`, or none asked.
pub fn plan(m: &Manifest, shards: usize) -> Result<Vec<ShardSpec>> {
    let n = m.segments.len();
    if shards == 0 || shards > n {
        return Err(Error::refused(
            "shards",
            format!("{shards} shards asked for a map of {n} segments (1 to {n} possible)"),
            crate::error::Remedy::SmallerSegments,
        ));
    }
    let live: Vec<usize> = m.segments.iter().map(|s| s.live()).collect();
    let total: usize = live.iter().sum();
    let mut out = Vec::with_capacity(shards);
    let (mut seg, mut done) = (0, 0);
    for s in 0..shards {
        let start = seg;
        // the ideal end of this shard in images, leaving at least one segment per later shard
        let target = total * (s + 1) / shards;
        let mut len = live[seg];
        seg += 1;
        while seg < n - (shards - s - 1) && done + len + live[seg] / 2 < target {
            len += live[seg];
            seg += 1;
        }
        if s == shards - 1 {
            len += live[seg..].iter().sum::<usize>();
            seg = n;
        }
        out.push(ShardSpec { segments: start..seg, global_start: done, len, generation: m.generation });
        done += len;
    }
    Ok(out)
}

impl Map {
    /// Opens the segments `segments` of the map in `dir` alone, as a map of their live images
    /// (reference `i` here is reference `global_start + i` of the whole map). With `generation`,
    /// fails if the map has been changed since (add, remove or compact commit a new one): the
    /// caller plans again.
    pub fn open_range(dir: &Path, segments: Range<usize>, generation: Option<u64>) -> Result<(Map, ShardSpec)> {
        let mut m = manifest::read_existing(dir)?;
        let path = dir.join(manifest::MANIFEST);
        if let Some(g) = generation.filter(|&g| g != m.generation) {
            return Err(Error::invalid(
                path.display().to_string(),
                format!("the map is at generation {}, the shard was planned at {g}: plan again", m.generation),
            ));
        }
        if segments.start >= segments.end || segments.end > m.segments.len() {
            return Err(Error::invalid(path.display().to_string(), format!("segments {segments:?} asked for, the map has {}", m.segments.len())));
        }
        let global_start = m.segments[..segments.start].iter().map(|s| s.live()).sum();
        let generation = m.generation;
        m.segments = m.segments[segments.clone()].to_vec();
        let map = Map::open_generation(dir, m)?;
        let spec = ShardSpec { segments, global_start, len: map.len(), generation };
        Ok((map, spec))
    }

    /// The map in `dir` without any of its segments: its manifest (config, keypoint network
    /// record) and its codebook, checked, as a map that serves no image. What a driver needs to
    /// encode queries (`Encoder::for_map`) when the segment files live on the shards' nodes; no
    /// segment file is opened, so none needs to be there.
    pub fn open_header(dir: &Path) -> Result<Map> {
        let mut m = manifest::read_existing(dir)?;
        m.segments.clear();
        Map::open_generation(dir, m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::SegmentEntry;

    /// A manifest whose segments hold `live` images each (a segment of 0 holds one removed image).
    fn manifest_with(live: &[usize]) -> Manifest {
        let config = crate::config::Config::default().encoding();
        let segments = live
            .iter()
            .enumerate()
            .map(|(i, &n)| SegmentEntry {
                file: format!("segment-{i}.safetensors"),
                images: n.max(1),
                trees: 0,
                keypoints: 0,
                bytes: 0,
                sha256: "0".repeat(64),
                removed: if n == 0 { vec![0] } else { vec![] },
                traversal: 0,
                index: None,
            })
            .collect();
        Manifest {
            format: "semlook-map".into(),
            version: 3,
            generation: 7,
            uid: "u".into(),
            created_by: "test".into(),
            neighbour_slots: config.local.neighbours,
            config,
            appearance_dim: 0,
            hog_dim: 0,
            compact_hog_dim: 0,
            keypoint_dim: 0,
            appearance_block: 0,
            values: Default::default(),
            segments,
            codebook: None,
            appearance_model: None,
            without_labels: false,
            traversals: vec![],
            frame_intervals: Default::default(),
            index: None,
            embedding: None,
            null: None,
            profile: None,
            checksum: String::new(),
        }
    }

    #[test]
    fn plans_cover_every_segment_once_and_balance_images() {
        for live in [vec![10; 7], vec![1, 1, 1, 50, 1, 1], vec![5, 0, 0, 5], vec![3]] {
            let m = manifest_with(&live);
            for shards in 1..=live.len() {
                let p = plan(&m, shards).unwrap();
                assert_eq!(p.len(), shards);
                assert_eq!(p[0].segments.start, 0);
                assert_eq!(p.last().unwrap().segments.end, live.len());
                let mut start = 0;
                for s in &p {
                    assert!(s.segments.end > s.segments.start, "{live:?} {shards}: empty shard");
                    assert_eq!(s.global_start, start);
                    assert_eq!(s.len, live[s.segments.clone()].iter().sum::<usize>());
                    start += s.len;
                }
            }
            assert!(plan(&m, live.len() + 1).is_err());
            assert!(plan(&m, 0).is_err());
        }
        // ten equal segments in two shards: five each
        let p = plan(&manifest_with(&[4; 10]), 2).unwrap();
        assert_eq!((p[0].len, p[1].len), (20, 20));
    }
}
