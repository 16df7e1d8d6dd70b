//! The command line's words for what the engine says a caller can do ([`Remedy`]): library
//! messages speak of the API, this names the flags.

use semlook::error::{Error, Remedy};

/// The flags that act on `e`, if the engine names a remedy.
pub fn hint(e: &Error) -> Option<&'static str> {
    Some(match e.remedy()? {
        Remedy::AddResumeOrReplace => {
            "`semlook map add --map MAP` appends to it; `map build --resume` continues its build; `map build --force` replaces it"
        }
        Remedy::ResumeOrReplace => "`map build --resume` continues an interrupted build; `--force` replaces what is there",
        Remedy::BuildOrResume => "build it with `semlook map build --map MAP`, or continue an interrupted build with `--resume`",
        Remedy::GiveLabels => {
            "pass --labels DIR (label maps named like the images) or --segmenter MODEL.onnx; `semlook models` lists what is installed"
        }
        Remedy::GiveImagesOrNoAppearance => "pass --images DIR, or --no-appearance to encode label maps alone",
        Remedy::GiveKeypointModel => "pass --keypoints MODEL.onnx, or set models.keypoint_onnx in --config",
        Remedy::SmallerSegments => "build the map with a smaller `--segment-images N` (more segments)",
        Remedy::NameReferenceTraversal => "pass --reference-traversal NAME",
        Remedy::NameImageRoot => "pass --pairs-root DIR, a folder that holds the query and reference images",
        Remedy::RebuildWithLabels => {
            "`--setting hog`, `appearance` or `verified` run on this map; for the others build it again (`map build --force`) with --labels DIR or a segmenter (`semlook models`)"
        }
    })
}
