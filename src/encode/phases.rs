//! The encoding of a frame in phases, for the engine's GPU path (crate-private): the global
//! descriptor comes in (computed on the device), [`Encoder::encode_rest`] adds objects, forest
//! and the network's descriptors grouped for VLAD, and [`Encoder::finish`] takes the VLAD vectors
//! (computed on the device for a whole batch). The CPU path runs the same phases in one call.

use super::{Encoder, Loaded, NetworkRuns, StageTimes, VladInput};
use crate::appearance;
use crate::descriptors::EncodedImage;
use crate::error::{Error, Result};
use crate::local;
use crate::objects;
use crate::util::ms_since;
use semlook_kernels as kernels;
use std::time::Instant;

/// A frame encoded up to (not including) its VLAD vectors.
#[derive(Debug, Clone)]
pub(crate) struct Pending {
    pub image: EncodedImage,
    pub times: StageTimes,
    pub vlad: Option<VladInput>,
}

impl Encoder {
    /// Everything after the global descriptor (its stats are computed if not given): objects,
    /// forest, and the appearance network (its output given by a caller that ran it, e.g. on the
    /// device), and the embedding (given, with its milliseconds, by a caller that made it on the
    /// device); VLAD is left to [`Encoder::finish`].
    pub(crate) fn encode_rest(
        &self,
        id: &str,
        loaded: &Loaded,
        global: Vec<f32>,
        stats: Option<Vec<f32>>,
        global_ms: f64,
        ran: NetworkRuns<'_>,
    ) -> Result<Pending> {
        let NetworkRuns { keypoints, embedding: embedded } = ran;
        let t = Instant::now();
        let ssim = self.global.ssim;
        let global_stats = stats.unwrap_or_else(|| {
            let mut s = vec![0.0; ssim.stats_len()];
            kernels::ssim::ssim_stats(&ssim, &global, &mut s, &mut Default::default());
            s
        });
        let global_ms = global_ms + ms_since(t);
        let t = Instant::now();
        let objects = objects::extract_objects(&loaded.labels, &self.table, &self.cfg.objects);
        let forest = local::build_forest(&objects, &self.cfg.local);
        let forest_ms = ms_since(t);
        let mut times = StageTimes { global_ms, forest_ms, ..loaded.times };
        let (given, embedding_device_ms) = (embedded.is_some(), embedded.as_ref().map_or(0.0, |e| e.1));
        let embed = || -> Result<(Vec<f32>, f64)> {
            if let Some(e) = embedded {
                return Ok(e);
            }
            match (&self.embedder, &loaded.rgb) {
                (Some(e), Some(rgb)) => {
                    let t = Instant::now();
                    let v = e.embed(rgb).map_err(|err| err.named(|r| Error::invalid(format!("frame {id:?}"), r)))?;
                    Ok((v, ms_since(t)))
                }
                _ => Ok((vec![], 0.0)),
            }
        };
        let describe = |times: &mut StageTimes| -> Result<(Option<VladInput>, _)> {
            match (&self.appearance, &loaded.rgb) {
                (Some(a), Some(rgb)) => {
                    let t = Instant::now();
                    let (input, verification, network_ms) = a.describe(rgb, &loaded.labels, &objects, keypoints)?;
                    // a network run elsewhere (on the device) counts as it took there
                    let elsewhere = if network_ms.is_none() { keypoints.map_or(0.0, |f| f.network_ms) } else { 0.0 };
                    times.network_ms = network_ms.unwrap_or(elsewhere);
                    times.network_device_ms = elsewhere;
                    times.appearance_ms = ms_since(t) + elsewhere;
                    Ok((Some(input), verification))
                }
                (Some(_), None) => Err(Error::invalid(format!("frame {id:?}"), "appearance needs the RGB image")),
                _ => Ok((None, Default::default())),
            }
        };
        // a frame encoded alone (a stream's, outside any thread pool): the embedding runs beside
        // the appearance stage, each network on its own session (so the same values); inside the
        // pool each worker encodes frames of its own one after the other (Encoder::embedding_beside)
        let beside = !given && self.beside && rayon::current_thread_index().is_none() && self.embedder.is_some() && self.appearance.is_some();
        let ((vlad, verification), (embedding, embedding_ms)) = if beside {
            let t = Instant::now();
            let (described, embedded) = std::thread::scope(|sc| {
                let other = sc.spawn(embed);
                let described = describe(&mut times).map(|d| (d, ms_since(t)));
                (described, other.join().unwrap_or_else(|_| Err(Error::invalid(format!("frame {id:?}"), "the embedding's thread panicked"))))
            });
            let ((described, described_ms), embedded) = (described?, embedded?);
            // what ran here (a network run on the device is counted in appearance_ms, not here)
            times.overlap_ms = (described_ms + embedded.1 - ms_since(t)).max(0.0);
            (described, embedded)
        } else {
            (describe(&mut times)?, embed()?)
        };
        times.embedding_ms = embedding_ms;
        times.embedding_device_ms = embedding_device_ms;
        let compact_hog = match (self.compact_hog, &loaded.rgb) {
            (true, Some(rgb)) => {
                // rounded to f16, what a map stores: a stored image reads back the same
                let mut v = crate::global::hog::compact_hog(rgb);
                crate::values::round_through_f16(&mut v);
                v
            }
            (true, None) => return Err(Error::invalid(format!("frame {id:?}"), "the compact HOG needs the RGB image")),
            (false, _) => vec![],
        };
        let (width, height) = loaded.source_size;
        let hog = loaded.hog.clone().unwrap_or_default();
        let image = EncodedImage {
            id: id.to_string(),
            width,
            height,
            global,
            global_stats,
            forest,
            appearance: vec![],
            hog,
            embedding,
            compact_hog,
            keypoints: verification,
            pose: None,
        };
        Ok(Pending { image, times, vlad })
    }

    /// Completes a pending frame with its VLAD vectors (one vector of the encoder's appearance
    /// size per run of its [`VladInput`], the image's last); other counts fail, naming the image.
    pub(crate) fn finish(&self, mut p: Pending, vlad: Option<Vec<f32>>, vlad_ms: f64) -> Result<(EncodedImage, StageTimes)> {
        if let (Some(mut vectors), Some(input), Some(a)) = (vlad, &p.vlad, &self.appearance) {
            let dim = a.dim();
            let bad = |r: String| Error::invalid(format!("VLAD vectors of image {:?}", p.image.id), r);
            if vectors.len() != dim * input.offsets.len().saturating_sub(1) {
                return Err(bad(format!("{} values for {} runs of dimension {dim}", vectors.len(), input.offsets.len().saturating_sub(1))));
            }
            // the values a map stores (int8 blocks, one per centre): a stored image reads back the same
            if let Some(cb) = a.codebook() {
                crate::values::round_to_blocks(&mut vectors, cb.dim);
            }
            let image = vectors.split_off(vectors.len() - dim);
            let mut counts = appearance::object_counts(&input.offsets);
            counts.pop();
            p.image.forest.set_appearance(dim, vectors, counts, self.cfg.appearance.min_descriptors).map_err(|e| e.named(bad))?;
            p.image.appearance = image;
            p.times.appearance_ms += vlad_ms;
        }
        Ok((p.image, p.times))
    }
}
