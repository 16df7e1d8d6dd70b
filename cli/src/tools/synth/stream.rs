//! Synthetic streams: a dataset's query traversals driven again at a varying speed, with stops.
//! Frame `t` of a new traversal is frame `round(s_t)` of the source traversal, where the source
//! position `s` advances by a speed that swings smoothly between `speed_min` and `speed_max`
//! (a sine of random period and phase) and stands still for `stop_frames` frames at `stops`
//! points spread over the route. Each frame keeps its source frame's files, pose and ground
//! truth, so any dataset with ground truth becomes a stream benchmark (written as an `explicit`
//! dataset manifest that points at the source files).

use semlook::dataset::{Dataset, DatasetManifest, FrameSpec, TraversalSpec, MANIFEST};
use semlook::error::{Error, Result};
use semlook::util::SplitMix64;
use std::path::{Path, PathBuf};

/// How the vehicle drives the route again.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamProfile {
    /// Speed, in source frames per frame.
    pub speed_min: f64,
    pub speed_max: f64,
    /// Stops along the route, each `stop_frames` frames long.
    pub stops: usize,
    pub stop_frames: usize,
    pub seed: u64,
}

impl Default for StreamProfile {
    fn default() -> Self {
        StreamProfile { speed_min: 0.6, speed_max: 1.4, stops: 2, stop_frames: 20, seed: 1 }
    }
}

impl StreamProfile {
    pub fn validate(&self) -> Result<()> {
        let ok = self.speed_min.is_finite()
            && self.speed_max.is_finite()
            && 0.05 <= self.speed_min
            && self.speed_min <= self.speed_max
            && self.speed_max <= 8.0;
        if !ok {
            return Err(Error::invalid(
                "stream profile",
                format!("speeds {}..{} must satisfy 0.05 <= min <= max <= 8", self.speed_min, self.speed_max),
            ));
        }
        if self.stops > 1000 || self.stop_frames > 100_000 {
            return Err(Error::invalid("stream profile", "at most 1000 stops of at most 100000 frames"));
        }
        Ok(())
    }
}

/// The source frame of every frame of the new traversal, over a source traversal of `n` frames.
pub fn resample(n: usize, p: &StreamProfile) -> Vec<usize> {
    if n == 0 {
        return vec![];
    }
    let mut rng = SplitMix64::derive(p.seed, n as u64);
    let period = rng.range(25.0, 60.0);
    let phase = rng.range(0.0, std::f64::consts::TAU);
    let (mid, amp) = ((p.speed_min + p.speed_max) / 2.0, (p.speed_max - p.speed_min) / 2.0);
    // stops at evenly spread source positions, each shifted a little
    let mut stops: Vec<f64> = (0..p.stops)
        .map(|k| (k as f64 + 0.5) / p.stops as f64 * (n - 1) as f64 + rng.range(-0.1, 0.1) * n as f64 / (p.stops.max(1) as f64))
        .collect();
    stops.sort_by(f64::total_cmp);
    let (mut out, mut s, mut t) = (Vec::new(), 0.0f64, 0usize);
    while s.round() < n as f64 {
        let frame = (s.round() as usize).min(n - 1);
        out.push(frame);
        if stops.first().is_some_and(|&at| s >= at) {
            stops.remove(0);
            out.extend(std::iter::repeat_n(frame, p.stop_frames));
        }
        s += mid + amp * (std::f64::consts::TAU * t as f64 / period + phase).sin();
        t += 1;
    }
    out
}

/// Writes `out/semlook-dataset.json`: the reference traversal of `ds` as it is and every query
/// traversal resampled by `p` (named `<name>-stream`); returns the frames of the new queries.
pub fn write(ds: &Dataset, out: &Path, p: &StreamProfile) -> Result<usize> {
    p.validate()?;
    let abs = |path: &Option<PathBuf>| -> Result<Option<PathBuf>> {
        path.as_ref().map(|f| std::path::absolute(f).map_err(|e| Error::io(f, e))).transpose()
    };
    let spec = |f: &semlook::dataset::Frame, id: String, gt: Option<Vec<u32>>| -> Result<FrameSpec> {
        Ok(FrameSpec { id, image: abs(&f.source.image)?, labels: abs(&f.source.labels)?, pose: f.pose, ground_truth: gt })
    };
    let reference = TraversalSpec::Explicit {
        name: ds.reference.name.clone(),
        frames: ds.reference.frames.iter().map(|f| spec(f, f.source.id.clone(), None)).collect::<Result<_>>()?,
    };
    let mut queries = Vec::new();
    let mut total = 0;
    for (k, q) in ds.queries.iter().enumerate() {
        let gt = ds.ground_truth(q)?;
        let picks = resample(q.frames.len(), &StreamProfile { seed: p.seed.wrapping_add(k as u64), ..*p });
        total += picks.len();
        let frames = picks
            .iter()
            .enumerate()
            .map(|(t, &i)| spec(&q.frames[i], format!("{}@{t:05}", q.frames[i].source.id), Some(gt[i].clone())))
            .collect::<Result<_>>()?;
        queries.push(TraversalSpec::Explicit { name: format!("{}-stream", q.name), frames });
    }
    let manifest = DatasetManifest {
        format: "semlook-dataset".into(),
        version: 1,
        name: Some(format!("{}-stream", ds.name)),
        layout: "explicit".into(),
        camera: None,
        label_format: ds.label_format,
        label_ids: ds.label_ids.clone(),
        reference,
        queries,
        ground_truth: None,
    };
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let path = out.join(MANIFEST);
    let bytes = serde_json::to_vec_pretty(&manifest).map_err(|e| Error::invalid("dataset manifest", e.to_string()))?;
    std::fs::write(&path, bytes).map_err(|e| Error::io(&path, e))?;
    Ok(total)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resampled_routes_keep_order_speed_bounds_and_stops() {
        let p = StreamProfile::default();
        let picks = resample(200, &p);
        assert_eq!(*picks.first().unwrap(), 0);
        assert!(*picks.last().unwrap() >= 198, "{:?}", &picks[picks.len() - 3..]);
        assert!(picks.windows(2).all(|w| w[1] >= w[0]), "never backwards");
        // the longest run of one frame is a stop: 20 frames of it and its own
        let mut runs = vec![];
        let mut run = 1;
        for w in picks.windows(2) {
            if w[0] == w[1] {
                run += 1;
            } else {
                runs.push(run);
                run = 1;
            }
        }
        runs.push(run);
        assert_eq!(runs.iter().filter(|&&r| r >= 21).count(), 2, "{runs:?}");
        // mean speed about 1 source frame per frame outside the stops
        let moving = picks.len() - 40;
        assert!((moving as f64 - 200.0).abs() < 40.0, "{moving}");
        assert!(resample(0, &p).is_empty());
    }
}
