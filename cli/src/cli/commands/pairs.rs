//! `query --pairs`: hloc's retrieval pairs file of a query's results, images named as hloc
//! names them (see `semlook::hloc`).

use crate::cli::args::PairsArgs;
use semlook::descriptors::source::RefSource;
use semlook::descriptors::DescriptorSet;
use semlook::error::{Error, Result};
use semlook::hloc;
use semlook::input::FrameSource;
use semlook::map::Map;
use semlook::matching::QueryMatch;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// hloc's name of every query (by id) and map image (by index), and the pairs per query.
pub struct PairNames {
    queries: HashMap<String, String>,
    references: Vec<String>,
    k: usize,
}

impl PairNames {
    pub fn find(a: &PairsArgs, map: &Map, frames: &[FrameSource], top_k: usize) -> Result<PairNames> {
        let images: Vec<(&str, &Path)> = frames
            .iter()
            .map(|f| match &f.image {
                Some(p) => Ok((f.id.as_str(), p.as_path())),
                None => Err(Error::invalid(format!("query {:?}", f.id), "--pairs names query images: give --images or --dataset")),
            })
            .collect::<Result<_>>()?;
        let root = match &a.pairs_root {
            Some(r) => r.clone(),
            None => {
                let mut dirs: Vec<PathBuf> = a.references.clone();
                dirs.extend(images.iter().map(|(_, p)| p.parent().map(Path::to_path_buf).unwrap_or_default()));
                hloc::default_root(&dirs)?
            }
        };
        let mut queries = HashMap::new();
        for (id, path) in images {
            let name = hloc::image_name(&root, path)?;
            if let Some(other) = queries.insert(id.to_string(), name.clone()).filter(|o| *o != name) {
                return Err(Error::invalid(
                    format!("query {id:?}"),
                    format!("two query images have this id ({other}, {name}); hloc would need each apart"),
                ));
            }
        }
        let ids: Vec<&str> = (0..map.len()).map(|i| map.id(i)).collect();
        let references = hloc::reference_names(&ids, &a.references, &root)?;
        Ok(PairNames { queries, references, k: a.pairs_k.unwrap_or(top_k) })
    }

    /// Writes the pairs of `matches` (one per query of `queries`) to `path`; the number of pairs.
    pub fn write(&self, path: &Path, queries: &DescriptorSet, matches: &[QueryMatch]) -> Result<usize> {
        let mut rows = Vec::with_capacity(matches.len());
        for (id, m) in queries.ids.iter().zip(matches) {
            let q = self.queries.get(id).ok_or_else(|| Error::invalid(format!("query {id:?}"), "has no hloc name"))?;
            rows.push((q.clone(), m.ranked.iter().take(self.k).map(|c| self.references[c.reference as usize].clone()).collect::<Vec<_>>()));
        }
        let text = hloc::pairs_text(&rows);
        std::fs::write(path, &text).map_err(|e| Error::io(path, e))?;
        Ok(rows.iter().map(|r| r.1.len()).sum())
    }
}
